"""`opt2skill experiment table3`: the quick setting end to end at tiny sizes (real generation, training,
evaluation and sweeps), its resume, Table III's tests, and bad input."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import time

import numpy as np
import pytest

from eval_support import CLI
from opt2skill.errors import ConfigError, DataError
from opt2skill.eval.evaluate import load_run_policy
from opt2skill.eval.metrics import TrackingErrors
from opt2skill.eval.report import EvalReport, TrajectoryResult
from opt2skill.experiment.settings import claim_folder, resolve
from opt2skill.experiment.table import build_table, compare_reports

TINY = ["--setting", "quick", "--n-train", "1", "--n-test", "1", "--duration", "5", "--train-steps", "200",
        "--num-envs", "4", "--histories", "0,10", "--stairs", "0.08", "--slopes", "10", "--sweep-trials", "1",
        "--sweep-start", "0.3", "--workers", "2", "--quiet"]


@pytest.mark.slow
def test_quick_setting_writes_every_table_and_figure_and_resumes(tmp_path):
    out = tmp_path / "t3"
    loud = [arg for arg in TINY if arg != "--quiet"]  # the progress bars drawn, on stderr
    r = subprocess.run([CLI, "experiment", "table3", "--out", str(out), *loud], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    # the policies trained side by side: one bar over their environment steps, read from their logs, to the end
    assert "training: 100%" in r.stderr, r.stderr[-3000:]
    for path in ("table3.md", "table3.json", "table3-table2.md", "table3-table2.json", "fig3.png", "provenance.json",
                 "experiment.json"):
        assert (out / path).is_file(), path
    steps = {p.stem: json.loads(p.read_text()) for p in (out / "steps").glob("*.json")}
    assert len(steps) == 27 and all(s["status"] == "done" for s in steps.values()), {k: s["status"] for k, s in steps.items()}
    table = json.loads((out / "table3.json").read_text())
    assert [row["key"] for row in table["data"]] == ["to", "human", "ik"]
    assert [row["name"] for row in table["history"]] == ["Opt2Skill-hist10", "Opt2Skill-hist0"]
    for row in table["data"] + table["history"]:
        assert set(row["summary"]) == {"E_joint", "E_vel_x", "E_vel_yaw", "E_ee_hand", "E_ee_foot", "E_pos_x", "E_pos_y",
                                       "E_yaw"}
        assert np.isfinite(row["summary"]["E_ee_foot"]["mean"]) and row["paper"]["E_ee_foot"]["mean"] > 0
    assert set(table["tests"]) == {"TO vs IK-data", "TO vs human-data"}
    assert "signed-rank" in table["tests"]["TO vs IK-data"]["test"]
    # the same pipeline and budget for every policy; kinematic sources on the `pos` inputs
    runs = {k[len("train-"):]: s["result"] for k, s in steps.items() if k.startswith("train-")}
    assert len({r["env_steps"] for r in runs.values()}) == 1
    assert runs["ik"]["ablation"] == runs["human"]["ablation"] == "pos" and runs["hist0"]["history"] == 0
    # --workers 2: the four policies trained two at a time in their own processes, then recorded by their
    # steps; each pair evaluated (and a data row's policy swept) before the next pair trains
    assert r.stdout.count("training 2 policies, 2 at a time") == 2 and r.stdout.count(": ready (") == 4, r.stdout[-3000:]
    order = [line for line in r.stdout.splitlines() if "training 2 policies" in line or "evaluate " in line]
    assert ["training" in line for line in order] == [True, False, False, False, False] * 2, order
    shared = max(1, (os.cpu_count() or 1) // 2)  # the cores shared out: not every core in each process
    for key in runs:
        first = json.loads((out / "runs" / key / "run.json").read_text())["invocations"][0]
        assert first["threads"] == shared, (key, first)
    # IK and TO held-out references of the same index share their parameters
    to_report = json.loads((out / "eval" / "to" / "eval.json").read_text())
    ik_report = json.loads((out / "eval" / "ik" / "eval.json").read_text())
    assert to_report["trajectories"][0]["params"] == ik_report["trajectories"][0]["params"]
    assert "none used in training (held out)" in to_report["references"]["note"]
    # each policy also rolled out under Table II's randomization and noise, into a table of its own
    robust = json.loads((out / "eval" / "to-table2" / "eval.json").read_text())
    assert robust["options"]["randomize"] and robust["options"]["noise"] and not to_report["options"]["randomize"]
    assert robust["references"]["indices"] == to_report["references"]["indices"]
    table2 = json.loads((out / "table3-table2.json").read_text())
    assert "Table II" in table2["condition"] and "no randomization" in table["condition"]
    assert set(table2["tests"]) == set(table["tests"]) and [row["key"] for row in table2["data"]] == ["to", "human", "ik"]
    for source in ("to", "ik", "human"):
        for terrain in ("stairs", "slope"):
            sweep = json.loads((out / "sweeps" / f"{source}-{terrain}" / "sweep.json").read_text())
            assert len(sweep["success_rate"]) == 1 and len(sweep["trials"]) == 1
    provenance = json.loads((out / "provenance.json").read_text())
    assert provenance["provenance"]["robot_hash"] and provenance["settings"]["n_train"] == 1
    assert "Table III:" in r.stdout and "fig3.png" in r.stdout
    # Each finished policy's actor is kept beside its (uncommitted) checkpoints: where they are gone, the
    # run is evaluated with that actor, which acts as the newest checkpoint did.
    for key, result in runs.items():
        assert result["policy"] == str(out / "runs" / key / "final" / "model.pt"), (key, result)
    obs = np.random.default_rng(0).normal(size=(3, load_run_policy(out / "runs" / "to").policy.obs_dim))
    newest = load_run_policy(out / "runs" / "to").policy(obs)
    shutil.rmtree(out / "runs" / "to" / "checkpoints")
    final = load_run_policy(out / "runs" / "to")
    assert final.info["checkpoint"].endswith("final/model.pt") and final.info["iteration"] == runs["to"]["iteration"]
    assert np.array_equal(final.policy(obs), newest)
    # A rerun skips every finished step and rewrites none of them.
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "steps").glob("*.json")}
    start = time.perf_counter()
    again = subprocess.run([CLI, "experiment", "table3", "--out", str(out), *TINY], capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.count("skipped") == 27
    assert stamps == {p.name: p.stat().st_mtime_ns for p in (out / "steps").glob("*.json")}
    assert time.perf_counter() - start < 60


@pytest.mark.slow
def test_a_terminated_experiment_checkpoints_the_trainings_in_flight(tmp_path):
    """SIGTERM to the experiment's process alone (`kill PID`) ends the policies training side by side
    in their own processes at the end of their iteration in flight, each checkpointed at its last
    logged iteration, and the command exits as interrupted (130). Without it the trainings went on
    orphaned, or died with everything since their last periodic checkpoint."""
    from opt2skill.rl.checkpoint import latest

    out = tmp_path / "t3"
    args = list(TINY)
    args[args.index("--train-steps") + 1] = "10000000"  # far more than the test waits for
    stdout, stderr = tmp_path / "stdout", tmp_path / "stderr"  # files: a full pipe would block the trainings
    with open(stdout, "w") as o, open(stderr, "w") as e:
        proc = subprocess.Popen([CLI, "experiment", "table3", "--out", str(out), *args], stdout=o, stderr=e,
                                start_new_session=True)

    def logged() -> dict[str, int]:  # run -> iterations in its progress log (complete lines)
        found = {}
        for log in (out / "runs").glob("*/progress.jsonl"):
            found[log.parent.name] = sum(1 for line in log.read_text().splitlines(keepends=True) if line.endswith("\n"))
        return found

    try:
        deadline = time.monotonic() + 600
        while len(logged()) < 2 or min(logged().values()) < 2:
            assert proc.poll() is None, stderr.read_text()[-3000:]
            assert time.monotonic() < deadline, logged()
            time.sleep(0.2)
        seen = logged()
        os.kill(proc.pid, signal.SIGTERM)
        proc.wait(timeout=300)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, stderr.read_text()[-3000:]
    said = stdout.read_text()
    assert "stopping: the 2 trainings checkpoint at the end of their iteration" in said, said[-2000:]
    for key, lines in seen.items():
        last = json.loads((out / "runs" / key / "progress.jsonl").read_text().splitlines()[-1])["iteration"]
        newest = latest(out / "runs" / key)
        assert newest is not None and newest.name == f"model_{last:08d}.pt" and last >= lines, (key, newest, last, lines)


def _forget(out, *steps):
    for name in steps:
        (out / "steps" / f"{name}.json").unlink()


@pytest.mark.slow
def test_a_folder_carried_without_its_datasets_generates_them_again_and_checks_them(tmp_path):
    """An experiment folder moved without data/ resumes: a dataset a step still reads is generated
    again and must hold the recorded references (fingerprints and joint-position checksums)."""
    import shutil

    out = tmp_path / "t3"
    tiny = [*TINY, "--histories", "10", "--train-steps", "100"]
    assert subprocess.run([CLI, "experiment", "table3", "--out", str(out), *tiny], capture_output=True, text=True,
                          timeout=900).returncode == 0
    recorded = json.loads((out / "steps" / "data-ik-test.json").read_text())["result"]
    assert len(recorded["contents"]) == recorded["counts"]["accepted"] and len(recorded["contents"][0][0]) == 16
    shutil.rmtree(out / "data")  # every dataset gone; only the IK ones are read again (by the evaluation)
    _forget(out, "eval-ik", "table3")
    r = subprocess.run([CLI, "experiment", "table3", "--out", str(out), *tiny], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "data-ik-test: its dataset" in r.stdout and r.stdout.count("generating it again") == 2, r.stdout[-3000:]
    again = json.loads((out / "steps" / "data-ik-test.json").read_text())["result"]
    assert again["contents"] == recorded["contents"] and again["regenerated"] == 1
    assert (out / "eval" / "ik" / "eval.json").is_file() and not (out / "data" / "to_train").exists()
    # a regeneration stopped part way (one reference missing) is resumed, not read as it is
    from opt2skill.data.store import DatasetStore

    DatasetStore(out / "data" / "ik_test").files()[-1].unlink()
    _forget(out, "eval-ik")
    r = subprocess.run([CLI, "experiment", "table3", "--out", str(out), *tiny], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    n = len(recorded["contents"])
    assert f"data-ik-test: its dataset {out / 'data' / 'ik_test'} holds {n - 1} of its {n} references" in r.stdout, r.stdout[-3000:]
    again = json.loads((out / "steps" / "data-ik-test.json").read_text())["result"]
    assert again["contents"] == recorded["contents"] and again["regenerated"] == 2
    # references that differ from the recorded ones stop the experiment, naming the dataset
    marker = out / "steps" / "data-ik-test.json"
    entry = json.loads(marker.read_text())
    entry["result"]["contents"][0][1] *= 1.001
    marker.write_text(json.dumps(entry))
    shutil.rmtree(out / "data" / "ik_test")
    _forget(out, "eval-ik")  # the training set is there: only the held-out one is generated
    bad = subprocess.run([CLI, "experiment", "table3", "--out", str(out), *tiny], capture_output=True, text=True,
                         timeout=900)
    assert bad.returncode != 0 and "ik_test was generated again but holds other references" in bad.stderr, bad.stderr[-2000:]
    assert "1 with other joint positions" in bad.stderr


def test_bad_setting_is_one_clear_error(tmp_path):
    r = subprocess.run([CLI, "experiment", "table3", "--setting", "paper", "--out", str(tmp_path / "x")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.strip() == "error: unknown setting 'paper'; settings: quick, full", r.stderr
    assert not (tmp_path / "x").exists()
    with pytest.raises(ConfigError, match="--n-train and --n-test must be >= 1"):
        resolve("quick", {"n_train": 0})
    with pytest.raises(ConfigError, match="--to-ablation must be one of pos, pos_f, pos_t, pos_f_t, got 'torque'"):
        resolve("quick", {"to_ablation": "torque"})
    with pytest.raises(ConfigError, match=r"history 10 \(--history\) must be one of --histories \[0, 5\]"):
        resolve("quick", {"histories": (0, 5)})
    r = subprocess.run([CLI, "experiment", "table3", "--history", "3", "--out", str(tmp_path / "y")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "history 3 (--history) must be one of --histories [0, 5, 10, 15]" in r.stderr, r.stderr
    assert not (tmp_path / "y").exists()
    r = subprocess.run([CLI, "experiment", "table3", "--train-seed", "-1", "--out", str(tmp_path / "z")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.strip() == "error: --train-seed must be >= 0, got -1", r.stderr
    assert not (tmp_path / "z").exists()


def test_the_data_rows_train_at_the_chosen_history_and_the_notes_say_so(tmp_path):
    from opt2skill.experiment.steps import Steps
    from opt2skill.experiment.table3 import _data_notes, history_note, policies

    s = resolve("quick", {"history": 0, "histories": (0,)})
    assert policies(s) == {"to": ("to", 0), "ik": ("ik", 0), "human": ("human", 0)}  # every source alike, no extra rows
    assert history_note(s) == " (the paper's data rows: 10; --history)"
    assert history_note(resolve("quick")) == ""
    note = _data_notes(s, Steps(tmp_path, total=1))[-1]  # the table's note on the pipeline names it
    assert "seed 0, the data rows at history 0 (the paper's data rows: 10; --history)" in note
    # The paper's default: the data rows at 10, the other histories as TO ablation rows.
    assert policies(resolve("quick")) == {"to": ("to", 10), "ik": ("ik", 10), "human": ("human", 10),
                                          "hist0": ("to", 0), "hist5": ("to", 5), "hist15": ("to", 15)}


def test_every_policy_of_an_experiment_trains_with_its_settings_options(tmp_path):
    from opt2skill.envs.config import tracking_config
    from opt2skill.experiment.runner import train_request, training_note

    data = {"dataset": str(tmp_path / "data" / "to_train")}
    for mixed in (False, True):
        s = resolve("quick", {"mixed_precision": mixed})
        request = train_request(s, tmp_path, "to", data, "pos_f_t", 10, "opt2skill experiment table3", threads=1)
        assert request.out == tmp_path / "runs" / "to" and request.steps == s.train_steps and request.threads == 1
        assert request.ppo().mixed_precision is mixed and request.device == s.device
        assert ("bf16" in training_note(s)) is mixed  # the tables' notes say how the updates computed
    # The base-position term and each world's noise share reach every policy's environment, and the notes.
    for base_position, noise_min, weighted in (("task", 1.0, False), ("on", 0.0, True)):
        s = resolve("quick", {"base_position": base_position, "noise_min": noise_min})
        request = train_request(s, tmp_path, "ik", data, "pos", 10, "opt2skill experiment table3")
        config = tracking_config("walk", request.ablation, request.history, request.kp_scale, request.sampling,
                                 request.base_position, request.rewards, request.noise_min)
        assert (config.rewards.base_pos.weight > 0) is weighted  # the walk task alone does not track it
        assert config.observations.noise.per_world_min == noise_min
        assert ("--base-position" in training_note(s)) is weighted and ("--noise-min" in training_note(s)) is weighted
    # Reward terms changed from Table I reach every policy's environment, and the notes.
    s = resolve("quick", {"rewards": (("base_lin_vel", 0.3, 8.0), ("base_ori", 0.5, None))})
    request = train_request(s, tmp_path, "human", data, "pos", 10, "opt2skill experiment table3")
    rewards = tracking_config("walk_human", request.ablation, request.history, request.kp_scale, request.sampling,
                              request.base_position, request.rewards, request.noise_min).rewards
    assert (rewards.base_lin_vel.weight, rewards.base_lin_vel.scale) == (0.3, 8.0)
    assert (rewards.base_ori.weight, rewards.base_ori.scale) == (0.5, 50.0)  # its own scale kept
    assert "base_lin_vel term at weight 0.3, kernel scale 8 (--reward)" in training_note(s)
    assert "--reward" not in training_note(resolve("quick"))
    with pytest.raises(ConfigError, match="--reward: unknown term 'speed'"):
        resolve("quick", {"rewards": (("speed", 1.0, None),)})
    with pytest.raises(ConfigError, match="--reward contact_force: this ablation has no reference contact forces"):
        resolve("quick", {"rewards": (("contact_force", 0.2, None),)})  # IK and human train with Pos inputs
    # A replicate: every policy trains with its own seed on the same references, and the notes say so.
    s = resolve("quick", {"seed": 3, "train_seed": 7})
    assert train_request(s, tmp_path, "to", data, "pos_f_t", 10, "opt2skill experiment table3").seed == 7
    assert "training seed 7, the references' 3 (--train-seed)" in training_note(s)
    assert train_request(resolve("quick", {"seed": 3}), tmp_path, "to", data, "pos_f_t", 10, "x").seed == 3
    assert "--train-seed" not in training_note(resolve("quick", {"seed": 3, "train_seed": 3}))
    with pytest.raises(ConfigError, match="--train-seed must be >= 0, got -1"):
        resolve("quick", {"train_seed": -1})
    with pytest.raises(ConfigError, match=r"--noise-min must be a share in \[0, 1\] .*, got 1.5"):
        resolve("quick", {"noise_min": 1.5})
    with pytest.raises(ConfigError, match="--base-position must be one of task, on, off, got 'yes'"):
        resolve("quick", {"base_position": "yes"})


def test_a_folder_of_another_experiment_or_other_files_is_refused(tmp_path):
    claim_folder(tmp_path / "a", resolve("quick"))
    claim_folder(tmp_path / "a", resolve("quick"))  # the same settings: resumes
    with pytest.raises(ConfigError, match=r"holds another experiment \(n_train: 3 there, 5 now\)"):
        claim_folder(tmp_path / "a", resolve("quick", {"n_train": 5}))
    with pytest.raises(ConfigError, match="holds another experiment .*setting: 'quick' there, 'full' now"):
        claim_folder(tmp_path / "a", resolve("full"))
    older = json.loads((tmp_path / "a" / "experiment.json").read_text())
    del older["device"], older["mixed_precision"], older["base_position"], older["noise_min"], older["rewards"], \
        older["train_seed"]  # made before these
    # settings existed: they count as their defaults there
    (tmp_path / "a" / "experiment.json").write_text(json.dumps(older))
    claim_folder(tmp_path / "a", resolve("quick"))
    with pytest.raises(ConfigError, match=r"rewards: \[\] there, \[\['base_lin_vel', 0.3, 8.0\]\] now"):
        claim_folder(tmp_path / "a", resolve("quick", {"rewards": (("base_lin_vel", 0.3, 8.0),)}))
    with pytest.raises(ConfigError, match="train_seed: None there, 1 now"):
        claim_folder(tmp_path / "a", resolve("quick", {"train_seed": 1}))
    with pytest.raises(ConfigError, match="mixed_precision: False there, True now"):
        claim_folder(tmp_path / "a", resolve("quick", {"mixed_precision": True}))
    with pytest.raises(ConfigError, match="to_ablation: 'pos_f_t' there, 'pos' now"):
        claim_folder(tmp_path / "a", resolve("quick", {"to_ablation": "pos"}))
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "notes.txt").write_text("mine")
    with pytest.raises(DataError, match="is not empty and is not an experiment folder"):
        claim_folder(tmp_path / "b", resolve("quick"))


def _report(name: str, foot_by_index: dict[int, float]) -> EvalReport:
    results = []
    for index, foot in foot_by_index.items():
        e = TrackingErrors(0.03, 5.0, 0.05, 2.0, foot, 1.0, 0.05, 0.02, float("nan"), 1.0, 100, False, pace=1.01,
                           turn=0.1 if index % 4 == 0 else -0.1, lead=0.02 + 0.01 * (index % 2))
        results.append(TrajectoryResult(index, {}, False, "time_out", 100, 100, e))
    return EvalReport("eval", {"name": name}, {"note": ""}, {}, results)


def test_table_pairs_to_and_ik_by_index_and_tests_human_unpaired():
    to = _report("to", {i: 5.0 + 0.1 * i for i in range(8)})
    ik = _report("ik", {i: 6.0 + 0.1 * i + 0.01 * (i % 3) for i in range(1, 9)})  # index 8 has no TO pair
    human = _report("human", {100 + i: 9.0 + i for i in range(5)})
    paired = compare_reports(to, ik, paired=True)
    assert paired["n"] == "7 pairs" and paired["p"]["E_ee_foot"] == pytest.approx(0.015625)  # 2 / 2^7: all one sign
    assert np.isnan(paired["p"]["E_joint"])  # every difference zero
    unpaired = compare_reports(to, human, paired=False)
    assert unpaired["n"] == "8 vs 5" and unpaired["p"]["E_ee_foot"] < 0.01
    table = build_table("quick", {"to": to, "ik": ik, "human": human}, {"hist0": "no training references"},
                        (0, 10), 10)
    md = table.markdown()
    assert "smoke result" in md and "not available: no training references" in md and "*paper: IK-data*" in md
    assert "| 100% of 8 | 1.01 | +0.025 | 2 / 6 |" in md and table.to_dict()["data"][0]["pace"]["n"] == 8  # the signed drift
    assert table.to_dict()["data"][0]["turn"]["left"] == 2  # and which way the policy turned
    assert table.to_dict()["data"][0]["lead"]["median"] == pytest.approx(0.025)  # and how fast ahead
    assert [r.report for r in table.history_rows] == [to, None]
    # Each test says which way it goes and whether TO is at or below the baseline on the claim metrics.
    assert paired["shift"]["E_ee_foot"] == pytest.approx(-1.0, abs=0.02) and paired["claim"]["met"]
    assert paired["claim"]["lower"] == ["E_ee_foot"] and paired["claim"]["higher"] == []
    assert unpaired["shift"]["E_ee_foot"] == pytest.approx(5.35 - 11.0) and unpaired["claim"]["met"]
    assert "| 0.016 lower |" in md and "TO at or below IK-data on E_ee-hand, E_ee-foot, E_pos-x" in md
    assert "): **met**; lower on E_ee-foot (0.016)." in md
    better_ik = _report("ik", {i: 4.0 + 0.1 * i + 0.01 * (i % 3) for i in range(8)})
    worse = compare_reports(to, better_ik, paired=True)
    assert not worse["claim"]["met"] and worse["claim"]["higher"] == ["E_ee_foot"]
    md = build_table("quick", {"to": to, "ik": better_ik, "human": human}, {}, (10,), 10).markdown()
    assert "**not met**: higher on E_ee-foot (0.0078)" in md and "| 0.0078 higher |" in md
    assert json.loads(json.dumps(build_table("quick", {"to": to, "ik": ik, "human": None}, {}, (10,), 10)
                                 .to_dict()))["tests"]["TO vs IK-data"]["claim"]["met"] is True


def test_a_human_folder_is_split_into_training_and_held_out_clips(tmp_path):
    from opt2skill.experiment.sources import build, human_files
    from opt2skill.experiment.steps import Unavailable
    from opt2skill.retarget.synthetic import write_walking_clips

    clips = write_walking_clips(tmp_path / "amass", 5, 0, (0.5, 1.0), (0.12, 0.16), 2.0, 1.0)
    (tmp_path / "amass" / "notes.txt").write_text("not a clip")
    s = resolve("quick", {"human": str(tmp_path / "amass"), "n_test": 2})
    assert human_files(s, tmp_path, "train", 3, 0) == clips[:3]
    assert human_files(s, tmp_path, "test", 2, 1) == clips[3:]
    few = resolve("quick", {"human": str(tmp_path / "amass"), "n_test": 5})
    with pytest.raises(Unavailable, match="human train: no clips .*has 5 files; 5 are held out"):
        build("human", "train", few, tmp_path / "out", progress=False)
    with pytest.raises(ConfigError, match="--human .* is not a folder"):
        resolve("quick", {"human": str(tmp_path / "missing")})


def test_a_source_is_topped_up_to_its_count_of_accepted_references(tmp_path):
    """`--n-test 2` counts accepted clips: where the first two lose one to validation (fast constructed
    clips exceed the knees' speed), the next clips are retargeted into the same dataset (the first
    ones keep their indices) until two are accepted; where too few pass, it stops at three clips per
    one wanted and says how short it is; a rerun tries nothing new."""
    from opt2skill.data.reader import Dataset
    from opt2skill.experiment.sources import TOP_UP_LIMIT, build

    s = resolve("quick", {"n_test": 2, "speed": (0.7, 1.3)})
    first = build("human", "test", s, tmp_path / "ok", progress=False)
    assert first["wanted"] == 2 and first["counts"]["accepted"] >= 2
    assert first["requested"] > 2 and first["counts"]["rejected"] >= 1  # the first two were not enough
    names = json.loads((tmp_path / "ok" / "data" / "human_test" / "dataset.json").read_text())["identity"]["files"]
    assert names == [f"synthetic_001_{i:05d}.npz" for i in range(first["requested"])]
    assert len(Dataset.open(tmp_path / "ok" / "data" / "human_test")) == first["counts"]["accepted"]
    again = build("human", "test", s, tmp_path / "ok", progress=False)
    assert (again["requested"], again["counts"]) == (first["requested"], first["counts"])

    fast = resolve("quick", {"n_test": 2, "speed": (0.9, 1.5)})
    short = build("human", "test", fast, tmp_path / "short", progress=False)
    assert short["requested"] == TOP_UP_LIMIT * 2 and short["counts"]["accepted"] < 2


def test_side_by_side_training_reads_its_progress_from_the_runs_logs(tmp_path):
    """The bar over policies trained in other processes counts each run's distillation and PPO
    steps from the last complete line of their progress logs (a line being written is skipped),
    and starts a resumed run where it restarts: lines logged after its newest checkpoint count only
    once the run has rewritten its log."""
    from opt2skill.experiment.runner import _LoggedSteps
    from opt2skill.rl.checkpoint import checkpoint_dir
    from opt2skill.rl.run import trim_progress

    run = tmp_path / "run"
    assert _LoggedSteps(run).count() == 0  # nothing logged yet
    for stage, iteration in ((run / "distill", 2), (run, 1)):  # the newest checkpoints (only their names are read)
        checkpoint_dir(stage).mkdir(parents=True)
        (checkpoint_dir(stage) / f"model_{iteration:08d}.pt").touch()
    (run / "distill" / "progress.jsonl").write_text('{"iteration": 1, "env_steps": 100}\n{"iteration": 2, "env_steps": 300}\n')
    (run / "progress.jsonl").write_text('{"iteration": 1, "env_steps": 50}\n{"iteration": 2, "env_steps": 100}\n'
                                        '{"iteration": 3, "env_steps": 150}\n{"iteration": 4, "env_st')
    steps = _LoggedSteps(run)  # killed at iteration 3, checkpointed at 1: the PPO stage restarts at 50 steps
    assert steps.count() == 300 + 50
    with open(run / "progress.jsonl", "a") as log:  # still the killed run's file: not yet counted
        log.write('{"iteration": 4, "env_steps": 200}\n')
    assert steps.count() == 300 + 50
    trim_progress(run, 1)  # the resumed run rewrites its log, then logs its next iteration
    with open(run / "progress.jsonl", "a") as log:
        log.write('{"iteration": 2, "env_steps": 100}\n')
    assert steps.count() == 300 + 100
    assert _LoggedSteps(run).count() == 300 + 50  # another launch now would restart from the checkpoint again


def test_fig3_counts_falls_apart_from_success(tmp_path):
    """A policy that lags its reference fails every setting without falling: Fig. 3's second row
    shows that (the share of trials without a fall), from the sweeps' own trials."""
    from opt2skill.experiment.figure import plot_fig3, stayed_up

    def trial(fell, progress):
        return {"yaw": 0.0, "fell": fell, "fall_time": 1.0 if fell else None, "progress": progress, "distance": 5.0,
                "success": not fell and progress >= 4.5}

    lagging = {"settings": {"values": [0.0, 0.02]}, "success_rate": {"0 cm": 0.0, "2 cm": 0.0},
               "trials": {"0 cm": [trial(False, 3.3)] * 4, "2 cm": [trial(False, 3.0)] * 3 + [trial(True, 1.0)]}}
    assert stayed_up(lagging).tolist() == [100.0, 75.0]
    path = plot_fig3({"stairs": {"to": None, "human": lagging}, "slope": {}}, tmp_path / "fig3.png", "test")
    assert path.stat().st_size > 10_000


def _replicate(folder, train_seed, foot_shift: float, skip: tuple[str, ...] = (), **changes):
    """A Table III folder as a finished run leaves it (identity, eval steps, reports), without training:
    TO's feet 1 cm below IK's on every reference, `foot_shift` added to every source."""
    from opt2skill.experiment.table3 import TABLE_II_SUFFIX, eval_dir, policies

    settings = resolve("quick", {"train_seed": train_seed, **changes})
    folder.mkdir()
    (folder / "experiment.json").write_text(json.dumps({"experiment": "table3", **settings.identity()}))
    (folder / "steps").mkdir()
    feet = {"to": 5.0, "ik": 6.0, "human": 8.0}
    for key in policies(settings):
        for suffix in ("", TABLE_II_SUFFIX):
            name = f"{key}{suffix}"
            if key in skip:
                status, result = "unavailable", {"reason": "no training references"}
            else:
                base = feet.get(key, 5.0) + foot_shift
                report = _report(key, {i: base + 0.1 * i for i in range(6)} if key != "human" else
                                 {100 + i: base + 0.3 * i for i in range(5)})
                path, _ = report.write(eval_dir(folder, name))
                status, result = "done", {"report": str(path)}
            (folder / "steps" / f"eval-{name}.json").write_text(json.dumps({"step": f"eval-{name}", "status": status,
                                                                           "result": result}))
    return folder


def test_replicates_pool_into_one_table_paired_within_each_and_others_are_refused(tmp_path):
    """`experiment table3-pool`: the rollouts of experiments that differ only in --train-seed make one
    table (TO and IK paired within each replicate), with its own missing rows; a replicate of the data
    rows alone pools them and leaves out the history rows; a folder of other settings, a seed used
    twice or a single folder is one clear error."""
    def cli(*args):
        return subprocess.run([CLI, "experiment", "table3-pool", *map(str, args)], capture_output=True, text=True,
                              timeout=120, env={**os.environ, "COLUMNS": "250"})

    a = _replicate(tmp_path / "a", None, 0.0)
    b = tmp_path / "b"
    _replicate(tmp_path / "b-before", 1, 0.5, skip=("hist0",)).rename(b)  # moved: its steps name the old paths
    result = cli(a, b, "--out", tmp_path / "pooled")
    assert result.returncode == 0, result.stderr
    md = (tmp_path / "pooled" / "table3-pooled.md").read_text()
    assert "| TO vs IK-data | Wilcoxon signed-rank, paired by generation index | 12 pairs |" in md
    assert "| 12 vs 10 |" in md and "100% of 12" in md
    assert "Pooled over 2 replicates (training seeds 0, 1;" in md and "b: no training references" in md
    table2 = json.loads((tmp_path / "pooled" / "table3-pooled-table2.json").read_text())
    assert table2["tests"]["TO vs IK-data"]["claim"]["met"] and table2["data"][0]["summary"]["E_ee_foot"]["n"] == 12
    data_rows_only = _replicate(tmp_path / "d", 3, 0.0, histories=(resolve("quick", {}).history,))
    result = cli(a, data_rows_only, "--out", tmp_path / "pooled-data-rows")
    assert result.returncode == 0, result.stderr
    md = (tmp_path / "pooled-data-rows" / "table3-pooled.md").read_text()
    assert "| TO vs IK-data | Wilcoxon signed-rank, paired by generation index | 12 pairs |" in md
    assert "hist0" not in md and "History rows 0, 5, 15 are left out" in md
    other = _replicate(tmp_path / "c", 2, 0.0, n_test=3)
    for folders, message in (([a, other], "is not a replicate of"), ([a, a], "trained with the same seed"),
                             ([a], "at least two replicate folders"), ([a, tmp_path / "none"], "not an experiment folder")):
        result = cli(*folders, "--out", tmp_path / "x")
        assert result.returncode == 2 and message in result.stderr and result.stderr.count("\n") == 1, result.stderr
    err = cli(a, other, "--out", tmp_path / "x").stderr
    assert "(they differ in n_test: " in err and f", 3 in {other})" in err
    assert not (tmp_path / "x").exists()
