"""Stairs: footholds on the treads, swings over the nosings, a real solve validated in its scene."""

import numpy as np
import pytest

from opt2skill.data.validate import validate
from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.scene.description import Scene
from opt2skill.tasks import get_task
from opt2skill.tasks.stairs import nosing_clearance, nosings, snap_between_nosings
from opt2skill.trajopt.skills.gait import Foothold, Step, stair_swing_reference

PARAMS = dict(step_height=0.1, tread=0.34, n_steps=1.0, down=0.0, speed=0.3, step_duration=0.5,
              double_support=0.25, clearance=0.1)


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


@pytest.fixture(scope="module")
def task(robot):
    return get_task("stairs", robot)


@pytest.mark.parametrize("overrides", [
    {}, {"n_steps": 4.0, "step_height": 0.15}, {"down": 1.0, "n_steps": 3.0, "tread": 0.30},
    {"speed": 0.6, "step_duration": 0.35, "n_steps": 5.0, "tread": 0.45},
])
def test_footholds_lie_on_the_step_surfaces(task, robot, overrides):
    gait, feet, scene = task.gait({**PARAMS, **overrides})
    edges = nosings(scene.terrain)
    half = robot.config.feet[0].half_length
    for step in gait.steps:
        x, y, z = step.target.position
        # the whole sole, and the margin, on one tread: no nosing under it
        assert np.all(np.abs(edges - x) >= half + task.config.edge_margin - 1e-9)
        sole = np.array([[x - half, y], [x + half, y]])
        assert np.allclose(scene.ground_height(sole), z - (feet[step.swing].position[2] - scene.ground_height(feet[step.swing].position[:2])), atol=1e-9)
    final = max(s.target.position[2] for s in gait.steps) if not overrides.get("down") else min(s.target.position[2] for s in gait.steps)
    n = int(round({**PARAMS, **overrides}["n_steps"]))
    h = {**PARAMS, **overrides}["step_height"]
    start = next(iter(feet.values())).position[2]
    assert final - start == pytest.approx(-n * h if overrides.get("down") else n * h, abs=1e-9)


def test_snapping_moves_a_sole_off_the_nosing_to_the_nearest_side():
    edges = np.array([1.0, 1.35])
    assert snap_between_nosings(0.5, edges, 0.15) == 0.5  # clear of every nosing: unchanged
    assert snap_between_nosings(0.9, edges, 0.15) == pytest.approx(0.85)
    assert snap_between_nosings(1.1, edges, 0.15) == pytest.approx(1.15)
    assert snap_between_nosings(1.3, edges, 0.15) == pytest.approx(1.2)
    assert snap_between_nosings(1.5, edges, 0.15) == pytest.approx(1.5)


def test_stair_swing_rises_first_then_crosses_then_lowers():
    a = Foothold("left_foot", np.array([0.0, 0.1, 0.0]), 0.0)
    b = Foothold("left_foot", np.array([0.6, 0.1, 0.15]), 0.0)
    step = Step(0.0, 0.2, 0.7, "left_foot", "right_foot", a, b)
    ts = np.linspace(0.2, 0.7, 2001)
    pos = np.array([stair_swing_reference(step, t, 0.08)[0] for t in ts])
    assert np.allclose(pos[0], a.position) and np.allclose(pos[-1], b.position)
    assert pos[:, 2].max() == pytest.approx(0.15 + 0.08)
    # by the time the foot has moved a tenth of the way across, it is above the target level
    assert pos[np.argmax(pos[:, 0] > 0.06), 2] > 0.15
    vel = np.array([stair_swing_reference(step, t, 0.08)[2] for t in ts])
    assert np.allclose(vel[[0, -1]], 0.0, atol=1e-9)
    numeric = np.gradient(pos, ts, axis=0)
    assert np.abs(numeric[5:-5] - vel[5:-5]).max() < 0.02


def test_nosing_clearance_sees_a_sole_through_the_step(task):
    gait, feet, scene = task.gait(PARAMS)
    step = next(s for s in gait.steps if s.target.position[2] > s.origin.position[2])
    edge = nosings(scene.terrain)[0]
    T = int(round(gait.duration / 0.005)) + 1
    corners = np.zeros((T, 2, 4, 3))
    i = [f.name for f in task.robot.config.feet].index(step.swing)
    mid = int(round(0.5 * (step.liftoff + step.touchdown) / 0.005))
    far = np.array([[-1.0, 0, 0.5], [-0.8, 0, 0.5], [-1.0, 0, 0.5], [-0.8, 0, 0.5]])
    corners[:] = far
    assert nosing_clearance(gait, corners, ["left_foot", "right_foot"], scene) > 0.3
    corners[mid, i] = [[edge - 0.1, 0.1, 0.05], [edge + 0.1, 0.1, 0.05], [edge - 0.1, 0.0, 0.05], [edge + 0.1, 0.0, 0.05]]
    assert nosing_clearance(gait, corners, ["left_foot", "right_foot"], scene) == pytest.approx(-0.05)


def test_bad_stairs_parameters_are_refused(task):
    with pytest.raises(ConfigError, match="step_height"):
        task.solve({**PARAMS, "step_height": 0.3}, seed=0)
    with pytest.raises(ConfigError, match="edge_margin"):
        get_task("stairs", task.robot, {"edge_margin": 0.2})


@pytest.mark.slow
def test_a_real_stair_climb_is_valid_in_its_scene(robot, task):
    """One 10-cm step up: Box-FDDP in receding windows, then the dataset's whole validation,
    MuJoCo replay on the stairs included, and the task's checks."""
    traj = task.solve(PARAMS, seed=3)
    assert traj.scene.terrain.step_height == 0.1 and traj.scene.terrain.n_steps == 1
    assert Scene.from_dict(traj.scene.to_dict()) == traj.scene
    errors = task.task_errors(traj)
    assert errors["nosing_clearance"]["value"] >= 0.02
    assert errors["flat_footing"]["value"] < 0.01
    result = validate(robot, traj, task_errors=errors)
    assert result["accepted"], result["reasons"]
    assert traj.qpos[-1, 2] - traj.qpos[0, 2] == pytest.approx(0.1, abs=0.03)


def test_stair_success_is_in_the_evaluation_report(tmp_path):
    """The task's registered metrics reach the report: a tracked copy that ends 10 cm low fails,
    one that ends on the reference's level succeeds; both survive the report's JSON round trip."""
    import dataclasses

    from opt2skill.data.record import build_trajectory
    from opt2skill.eval.metrics import tracking_errors
    from opt2skill.eval.report import EvalReport, TrajectoryResult, read_report
    from opt2skill.eval.task_metrics import task_metrics

    robot = load_robot("digit")
    T = 50
    qpos = np.tile(robot.mj_model.key_qpos[0], (T, 1))
    qpos[:, 2] += np.linspace(0.0, 0.2, T)
    zeros = np.zeros
    reference = build_trajectory(robot, qpos, zeros((T, robot.nv)), zeros((T, robot.nu)), zeros((T, 2, 6)),
                                 zeros((T, 2), bool), task="stairs", contact_names=("left_foot", "right_foot"),
                                 params=dict(PARAMS), seed=0)
    low = dataclasses.replace(reference, qpos=qpos - np.r_[0, 0, 0.1, np.zeros(robot.nq - 3)])
    assert task_metrics(reference, reference)["stair_success"] == (1.0, "")
    assert task_metrics(reference, low)["stair_success"] == (0.0, "")
    assert task_metrics(reference, low)["final_height_error"][0] == pytest.approx(10.0)
    results = [TrajectoryResult(i, {}, False, "time_out", T, T, tracking_errors(reference, t), task_metrics(reference, t))
               for i, t in enumerate((reference, low))]
    report = EvalReport("eval", {"name": "mine", "key": {}}, {"note": "2", "dataset": "d", "indices": [0, 1],
                        "fingerprints": ["a", "b"]}, {}, results)
    json_path, md_path = report.write(tmp_path)
    assert read_report(json_path).task_summary()["stair_success"][:3] == pytest.approx((0.5, 0.5, 2))
    assert "stair_success" in md_path.read_text()
