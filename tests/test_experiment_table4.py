"""`opt2skill experiment table4`: the quick setting end to end at tiny sizes (real wipe references,
training, evaluation per force level, the desk-height transfer, Table IV and Fig. 4), its resume;
Table IV's cells and tests from known values; the signed-rank test against an exact enumeration;
bad input."""

from __future__ import annotations

import itertools
import json
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from eval_support import CLI
from opt2skill.errors import ConfigError
from opt2skill.eval.metrics import TrackingErrors
from opt2skill.eval.report import EvalReport, TrajectoryResult
from opt2skill.eval.stats import signed_rank
from opt2skill.experiment import force_sets
from opt2skill.experiment.force_table import build_table
from opt2skill.experiment.settings import claim_folder, resolve
from opt2skill.experiment.table4_settings import Table4Settings

# One force level whose held-out set (desk pinned at 0.95 m) is also the transfer's reference: two
# wipe references in all, two of the four policies (the four rows' table is tested below from known
# values; the quick setting trains all four). The references are real solves stored in the repository
# (tests/data/table4/README.md): solving them takes 70 to 230 s on the loaded 2-core machine.
WIPES = Path(__file__).parent / "data" / "table4"
TINY = ["--setting", "quick", "--n-train", "1", "--n-test", "1", "--n-transfer", "1", "--forces", "15",
        "--desk-height", "0.95:0.95", "--transfer-desks", "0.9", "--ablations", "pos,pos_f_t", "--train-steps", "200",
        "--distill-steps", "200", "--num-envs", "4", "--workers", "2", "--quiet"]


def table4_settings(**overrides):
    return resolve("quick", overrides, kind=Table4Settings)


@pytest.mark.slow
def test_quick_setting_writes_table_iv_fig4_and_the_transfer_and_resumes(tmp_path):
    out = tmp_path / "t4"
    for dataset in WIPES.glob("force*"):  # reused as generated datasets of the same identity
        shutil.copytree(dataset, out / "data" / dataset.name)
    r = subprocess.run([CLI, "experiment", "table4", "--out", str(out), *TINY], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    for path in ("table4.md", "table4.json", "fig4.png", "provenance.json", "experiment.json"):
        assert (out / path).is_file(), path
    steps = {p.stem: json.loads(p.read_text()) for p in (out / "steps").glob("*.json")}
    # 2 datasets (the level's set is the transfer's), 2 trainings, 2 evaluations, 1 transfer, table, figure
    assert len(steps) == 9 and all(s["status"] == "done" for s in steps.values()), {k: s["status"] for k, s in steps.items()}
    assert all(steps[f"data-{d.name}"]["result"]["counts"] == {"accepted": 1, "rejected": 0, "failed": 0} for d in WIPES.glob("force*"))
    runs = {k[len("train-"):]: s["result"] for k, s in steps.items() if k.startswith("train-")}
    assert set(runs) == {"pos", "pos_f_t"} and len({r["env_steps"] for r in runs.values()}) == 1
    assert all(r["ablation"] == k for k, r in runs.items())
    # Each policy distilled the expert from the training set's gains (`--distill-steps`), then PPO.
    assert all(r["distill_env_steps"] >= 200 for r in runs.values())
    assert all((Path(r["run"]) / "distill" / "checkpoints").is_dir() for r in runs.values())
    # --workers 2: both policies trained at once in their own processes, then each step recorded its finished run
    assert "training 2 policies, 2 at a time" in r.stdout and r.stdout.count(": ready (") == 2, r.stdout[-3000:]
    table = json.loads((out / "table4.json").read_text())
    for metric in ("force_error", "force_error_raw", "right_hand_error"):
        for ablation in ("pos", "pos_f_t"):
            cell = table["cells"][metric][ablation]
            assert cell["15"]["n"] == 1 and np.isfinite(cell["15"]["mean"]) and cell["avg"]["mean"] == cell["15"]["mean"]
    assert table["paper"]["force_error"]["pos_f_t"]["avg"] == {"mean": 1.5, "sd": 2.6}
    assert table["paper"]["force_error_raw"] == {}  # the paper gives one force error: beside the sensor's view
    assert set(table["tests"]) == {"Pos+F+T vs Pos"} and table["tests"]["Pos+F+T vs Pos"]["pairs"] == 1
    # every policy tracked the same held-out reference, 15 N on a 0.95-m desk, none it trained on
    evals = [json.loads((out / "eval" / a / "f15" / "eval.json").read_text()) for a in ("pos", "pos_f_t")]
    assert evals[0]["trajectories"][0]["params"] == evals[1]["trajectories"][0]["params"]
    assert evals[0]["trajectories"][0]["params"]["force"] == 15.0 and "held out" in evals[0]["references"]["note"]
    (transfer,) = table["transfer"]
    assert transfer["desk_height"] == 0.9 and transfer["reference_desk_height"] == [0.95]
    assert transfer["references"][0]["reference_force"] == pytest.approx(15.0, abs=1.0)
    assert np.isfinite(transfer["hand_error_mean_sd"][0])
    _the_moved_desk_is_where_the_physics_has_it(out / "data" / "force15_desk0.95_seed1")
    with np.load(out / "eval" / "pos_f_t" / "f15" / "profiles.npz") as f:
        reference = f["reference_0"]
        assert np.median(reference[reference > 13.5]) == pytest.approx(15.0, abs=0.5) and len(f["tracked_0"]) >= 2
    assert "Table IV:" in r.stdout and "fig4.png" in r.stdout
    # A rerun skips every finished step and rewrites none of them.
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "steps").glob("*.json")}
    start = time.perf_counter()
    again = subprocess.run([CLI, "experiment", "table4", "--out", str(out), *TINY], capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.count("skipped") == 9
    assert stamps == {p.name: p.stat().st_mtime_ns for p in (out / "steps").glob("*.json")}
    assert time.perf_counter() - start < 60


def _the_moved_desk_is_where_the_physics_has_it(dataset):
    """The transfer's hook: a reference's scene with the desk moved puts the environment's desk top there."""
    import dataclasses

    import mujoco

    from opt2skill.data.reader import Dataset
    from opt2skill.envs import ReferenceBank, TrackingEnv, tracking_config
    from opt2skill.model import load_robot

    robot, reference, config = load_robot("digit"), Dataset.open(dataset)[0], tracking_config("wipe")
    for height in (0.95, 0.9):
        moved = dataclasses.replace(reference, scene=reference.scene.with_prop("desk", height=height))
        bank = ReferenceBank.from_trajectories(robot, [moved], config.observations.end_effectors)
        with TrackingEnv(robot, bank, config, 1, seed=0) as env:
            env.reset()
            model = env.sim.models[0]
            top = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "props_fixed_0")
            assert model.geom_pos[top, 2] + model.geom_size[top, 2] == pytest.approx(height)


def test_bad_table4_input_is_one_clear_error(tmp_path):
    r = subprocess.run([CLI, "experiment", "table4", "--setting", "paper", "--out", str(tmp_path / "x")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.strip() == "error: unknown setting 'paper'; settings: quick, full", r.stderr
    r = subprocess.run([CLI, "experiment", "table4", "--forces", "0,30", "--out", str(tmp_path / "x")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.strip() == (
        "error: --forces: parameter 'force' = 30 N is outside its allowed range [0, 25] N"), r.stderr
    assert not (tmp_path / "x").exists()
    with pytest.raises(ConfigError, match="--ablations must be distinct names from .* including pos_f_t"):
        table4_settings(ablations=("pos", "pos_f"))
    with pytest.raises(ConfigError, match="--timing: unknown config key 'timing.strok'"):
        table4_settings(timing={"strok": 0.5})
    with pytest.raises(ConfigError, match="--desk-height: parameter 'desk_height' = 2 m is outside"):
        table4_settings(desk_height=(0.9, 2.0))
    with pytest.raises(ConfigError, match="--n-train, --n-test and --n-transfer must be >= 1"):
        table4_settings(n_test=0)
    with pytest.raises(ConfigError, match=r"--distill-steps must be >= 0 \(0: PPO from scratch\), got -5"):
        table4_settings(distill_steps=-5)
    claim_folder(tmp_path / "t3", resolve("quick"))
    with pytest.raises(ConfigError, match="holds another experiment .*experiment: 'table3' there, 'table4' now"):
        claim_folder(tmp_path / "t3", table4_settings())


def test_every_level_shares_its_desk_heights_and_a_pinned_level_is_the_transfer_reference():
    s = table4_settings()
    roles = force_sets.roles(s)
    assert [roles[f"f{f:g}"][0].force for f in s.forces] == [(f, f) for f in s.forces]
    assert {roles[f"f{f:g}"][0].seed for f in s.forces} == {s.seed + 1} and roles["train"][0].seed == s.seed
    assert len(force_sets.datasets(s)) == 1 + 6 + 1
    pinned = table4_settings(desk_height=(0.95, 0.95), n_test=1, n_transfer=3)
    sets = force_sets.datasets(pinned)
    assert len(sets) == 1 + 6 and sets["force15_desk0.95_seed1"][1] == 3  # the larger of the two roles


def _report(values: dict[int, tuple[float, float]], fell: int | None = None) -> EvalReport:
    """index -> (force error, right hand error)."""
    results = []
    for index, (force, hand) in values.items():
        e = TrackingErrors(*([0.0] * 11), index == fell)
        metrics = {"force_error": (force, "N"), "right_hand_error": (hand, "cm"), "left_hand_error": (1.0, "cm")}
        results.append(TrajectoryResult(index, {}, False, "fell" if index == fell else "time_out", 100, 100, e, metrics))
    return EvalReport("eval", {"name": "x"}, {"note": ""}, {}, results)


def test_table_iv_cells_are_mean_and_sd_per_level_and_pooled_and_tests_pair_by_level_and_index():
    forces = (0.0, 10.0)
    best = {0.0: _report({0: (0.1, 2.0), 1: (0.3, 4.0)}), 10.0: _report({0: (1.0, 3.0), 1: (2.0, 3.0), 2: (3.0, 3.0)})}
    pos = {0.0: _report({0: (1.1, 2.0), 1: (1.3, 4.0)}, fell=1),
           10.0: _report({0: (9.0, 3.0), 1: (9.5, 3.0), 2: (8.0, 3.0), 3: (7.0, 3.0)})}  # index 3: no pair
    reports = {**{("pos_f_t", f): r for f, r in best.items()}, **{("pos", f): r for f, r in pos.items()}}
    table = build_table("quick", forces, ("pos", "pos_f", "pos_f_t"), reports, {"Pos+F at 0 N": "no trained policy"})
    cell = table.cells["force_error"]["pos_f_t"]
    assert cell["0"] == {"mean": pytest.approx(0.2), "sd": pytest.approx(np.std([0.1, 0.3], ddof=1)), "n": 2}
    assert cell["avg"]["mean"] == pytest.approx(np.mean([0.1, 0.3, 1.0, 2.0, 3.0]))
    assert cell["avg"]["sd"] == pytest.approx(np.std([0.1, 0.3, 1.0, 2.0, 3.0], ddof=1))
    assert table.cells["right_hand_error"]["pos"]["10"]["sd"] == 0.0
    test = table.tests["Pos+F+T vs Pos"]
    assert test["pairs"] == 5 and test["p"]["force_error"] == pytest.approx(2 / 2**5)  # five pairs, one sign
    assert np.isnan(test["p"]["right_hand_error"])  # every difference zero
    assert test["shift"]["force_error"] == pytest.approx(-5.0)  # median of -1, -1, -8, -7.5, -5: Pos+F+T lower
    assert table.falls == {"pos": "1 of 6", "pos_f": "0 of 0", "pos_f_t": "0 of 5"}
    assert np.isnan(table.tests["Pos+F+T vs Pos+F"]["p"]["force_error"]) and table.tests["Pos+F+T vs Pos+F"]["pairs"] == 0
    md = table.markdown()
    assert "smoke result" in md and "| Pos+F+T | 0.20 ± 0.14 | 2.00 ± 1.00 |" in md
    assert "| Pos+F+T vs Pos | 5 | 0.062 | - |" in md  # 5 pairs of one sign: p = 1/16, no direction at 0.05
    assert "| *paper: Pos* | *1.2 ± 2.1* | *8.7 ± 2.2* | *11.7 ± 8.3* |" in md
    assert "| Pos+F | - | - | - | 0 of 0 |" in md and "not available ('-' above): Pos+F at 0 N: no trained policy" in md


def _exact_signed_rank(d: np.ndarray) -> float:
    """Two-sided exact p of the signed-rank statistic by enumerating all 2^n sign patterns."""
    ranks = np.argsort(np.argsort(np.abs(d))) + 1.0
    observed = ranks[d > 0].sum()
    total = ranks.sum()
    stats = [sum(r for r, s in zip(ranks, signs) if s) for signs in itertools.product((0, 1), repeat=len(d))]
    extreme = min(observed, total - observed)
    return min(1.0, 2 * np.mean([s <= extreme for s in stats]))


def test_signed_rank_matches_an_exact_enumeration():
    x = np.array([1.83, 0.50, 1.62, 2.48, 1.68, 1.88, 1.55, 3.06, 1.30])
    y = np.array([0.878, 0.647, 0.598, 2.05, 1.06, 1.29, 1.06, 3.14, 1.29])
    assert signed_rank(x, y) == pytest.approx(_exact_signed_rank(x - y))
    assert signed_rank(x, y) == pytest.approx(0.0390625)  # Hollander & Wolfe's depression data: 2 * 10 / 512
    assert signed_rank([1.0, np.nan, 3.0, 2.0], [0.0, 1.0, 1.0, 1.5]) == pytest.approx(0.25)  # the NaN pair skipped
    assert np.isnan(signed_rank([1.0], [0.0])) and np.isnan(signed_rank([1.0, 2.0], [1.0, 2.0]))
