"""The evaluation commands on a real (briefly trained) run: eval writes its tables and plots, compare
puts two runs side by side with Wilcoxon p-values on the same references, sweep runs its trials,
render shows a rollout, and bad runs or datasets get one-line errors."""

from __future__ import annotations

import json
import shutil
import subprocess

import imageio
import numpy as np
import pytest
from envs_support import recorded_reference
from eval_support import CLI, gliding, shared_run, write_dataset

from opt2skill.data.reader import Dataset
from opt2skill.deploy.export import export_policy
from opt2skill.errors import ConfigError, DataError
from opt2skill.eval.compare import compare
from opt2skill.folder_lock import folder_lock
from opt2skill.eval.evaluate import EvalRequest, evaluate, load_run_policy
from opt2skill.eval.metrics import METRICS
from opt2skill.eval.sweep import SweepSettings, default_values


@pytest.fixture(scope="module")
def run_and_data(tmp_path_factory):
    return shared_run(tmp_path_factory)


def _cli(*args, timeout=600):
    return subprocess.run([CLI, *map(str, args)], capture_output=True, text=True, timeout=timeout)


def test_eval_writes_every_metric_the_papers_row_and_plots(run_and_data, tmp_path):
    run, data = run_and_data
    result = _cli("eval", run, "--split", "training", "--n", "2", "--plots", "1", "--out", tmp_path / "ev", "--quiet")
    assert result.returncode == 0, result.stderr
    report = json.loads((tmp_path / "ev" / "eval.json").read_text())
    assert report["kind"] == "eval" and [t["index"] for t in report["trajectories"]] == [0, 1]
    assert set(report["summary"]) == set(METRICS) and 0 <= report["success_rate"] <= 1
    assert report["policy"]["iteration"] == 2 and "NOT held out" in report["references"]["note"]
    assert all(t["seen_in_training"] for t in report["trajectories"])
    md = (tmp_path / "ev" / "eval.md").read_text()
    assert "Opt2Skill (paper, Table III)" in md and "reference line" in md and "E_ee-foot (cm)" in md
    assert (tmp_path / "ev" / "plots" / "track_000000.png").stat().st_size > 10_000
    assert "E_vel-x (cm/s)" in result.stdout and "success (falls counted)" in result.stdout
    # Every reference of this dataset was used in training: the default split says so and how to fix it.
    with pytest.raises(DataError, match="no held-out references.*--dataset"):
        evaluate(EvalRequest(run=run, n=2), progress=False)


def test_compare_two_runs_on_the_same_references(run_and_data, tmp_path):
    run, data = run_and_data
    older = tmp_path / "older"
    shutil.copytree(run, older, ignore=shutil.ignore_patterns("eval", "*.mp4"))
    (older / "checkpoints" / "model_00000002.pt").unlink()  # the same run one PPO iteration earlier
    out = tmp_path / "cmp"
    result = _cli("compare", run, older, "--split", "training", "--n", "3", "--out", out, "--quiet")
    assert result.returncode == 0, result.stderr
    cmp = json.loads((out / "compare.json").read_text())
    runs = cmp["runs"]
    assert [r["policy"]["iteration"] for r in runs] == [2, 1]
    assert [t["index"] for t in runs[0]["trajectories"]] == [t["index"] for t in runs[1]["trajectories"]] == [0, 1, 2]
    [pair] = cmp["wilcoxon_p"].values()
    assert set(pair) == set(METRICS)
    assert all(p is None or 0 < p <= 1 for p in pair.values()) and any(p is not None for p in pair.values())
    md = (out / "compare.md").read_text()
    assert "Wilcoxon signed-rank p-values" in md and "Opt2Skill (paper, Table III)" in md
    # Each test's direction: the median of the second run's errors minus the first's, reference by reference.
    [shift] = cmp["median_paired_difference"].values()
    joint = [[t["E_joint"] for t in r["trajectories"]] for r in runs]
    assert shift["E_joint"] == pytest.approx(float(np.median(np.subtract(joint[1], joint[0]))))
    # A second comparison reuses each run's evaluation of the same references.
    cached = older / "eval" / "squat3-given" / "eval.json"
    stamp = json.loads(cached.read_text())["created"]
    again = compare([run, older], split="training", n=3, progress=False)
    assert json.loads(cached.read_text())["created"] == stamp and again.reports[1].created == stamp
    stored = [np.nan if p is None else p for v in cmp["wilcoxon_p"].values() for p in v.values()]
    np.testing.assert_allclose([p for v in again.p_values.values() for p in v.values()], stored, equal_nan=True)
    # A run's eval folder that another command is writing: compared all the same, its cache left alone.
    busy = tmp_path / "busy"
    shutil.copytree(older, busy, ignore=shutil.ignore_patterns("eval"))
    folder = busy / "eval" / "squat3-given"
    with folder_lock(folder):
        during = compare([run, busy], split="training", n=3, progress=False)
    assert len(during.reports) == 2 and not (folder / "eval.json").exists()


def test_sweep_on_a_tiny_grid(run_and_data, tmp_path):
    run, data = run_and_data
    out = tmp_path / "sweep"
    first = run / "checkpoints" / "model_00000001.pt"  # an earlier checkpoint than the newest
    # A squat does not travel (a sweep refuses it): the same squat carried 2 m forward does.
    travelling = write_dataset(tmp_path / "glide", [gliding(Dataset.open(data)[0], 2.0)])
    result = _cli("sweep", run, "--terrain", "stairs", "--values", "0,0.1", "--trials", "2", "--out", out, "--quiet",
                  "--checkpoint", first, "--dataset", travelling)
    assert result.returncode == 0, result.stderr
    sweep = json.loads((out / "sweep.json").read_text())
    assert sweep["policy"]["iteration"] == 1
    assert list(sweep["success_rate"]) == ["0 cm", "10 cm"]
    trials = sweep["trials"]["10 cm"]
    assert len(trials) == 2 and all(abs(t["yaw"]) <= np.radians(25) for t in trials)
    assert [t["yaw"] for t in trials] == [t["yaw"] for t in sweep["trials"]["0 cm"]]  # paired trials
    assert (out / "sweep.png").stat().st_size > 5_000 and "| 10 cm |" in (out / "sweep.md").read_text()
    with pytest.raises(ConfigError, match="--terrain must be one of stairs, slope"):
        default_values("ice")
    with pytest.raises(ConfigError, match="slope angle must be in"):
        SweepSettings(terrain="slope", values=(45.0,)).check()
    assert default_values("stairs")[-1] == 0.16 and len(default_values("slope")) == 9


def test_render_a_runs_rollout_with_the_reference_ghost(run_and_data, tmp_path):
    run, data = run_and_data
    result = _cli("render", run, "--index", "1", "--fps", "10", "--out", tmp_path / "r.mp4",
                  "--checkpoint", run / "checkpoints" / "model_00000001.pt")
    assert result.returncode == 0, result.stderr
    assert "ghost: the reference" in result.stdout and "iteration 1)" in " ".join(result.stdout.split())
    frames = [f for f in imageio.get_reader(tmp_path / "r.mp4")]  # (list() asks the reader for an infinite length)
    assert len(frames) >= 3 and all(np.asarray(f).std() > 5 for f in frames)


def test_bad_runs_and_datasets_get_one_line_errors(run_and_data, tmp_path):
    run, data = run_and_data
    other_robot = tmp_path / "other_robot"
    shutil.copytree(run, other_robot, ignore=shutil.ignore_patterns("eval", "*.mp4"))
    spec = json.loads((other_robot / "run.json").read_text())
    spec["identity"]["robot_hash"] = "0" * 64
    (other_robot / "run.json").write_text(json.dumps(spec))
    with pytest.raises(DataError, match="trained on a different 'digit' robot file"):
        load_run_policy(other_robot)
    with pytest.raises(DataError, match="is not one of run .* evaluate the run it belongs to"):
        load_run_policy(run, other_robot / "checkpoints" / "model_00000002.pt")  # a checkpoint says not what it is for
    other_config = tmp_path / "other_config"
    shutil.copytree(run, other_config, ignore=shutil.ignore_patterns("eval", "*.mp4"))
    spec = json.loads((other_config / "run.json").read_text())
    spec["identity"]["tracking"]["observations"]["history"] = 5
    (other_config / "run.json").write_text(json.dumps(spec))
    # (checkpoints written since the trainer records what they are for say so; older ones by their input size)
    with pytest.raises(DataError, match=r"checkpoint of another policy: history 10 \(expected 5\)|takes 481 observations; .* gives 281"):
        export_policy(other_config, tmp_path / "p.onnx")
    other_task = write_dataset(tmp_path / "recorded", [recorded_reference(20)[0]])
    with pytest.raises(DataError, match="holds 'recorded' trajectories; the policy was trained on 'squat'"):
        evaluate(EvalRequest(run=run, dataset=other_task), progress=False)
    # On the command line: one line on stderr, status 2, no traceback.
    result = _cli("eval", tmp_path)
    assert result.returncode == 2 and "is not a training run" in result.stderr and "Traceback" not in result.stderr
    result = _cli("eval", run, "--dataset", other_task)
    assert result.returncode == 2 and "holds 'recorded' trajectories" in result.stderr and len(result.stderr.splitlines()) == 1
