"""The IK baseline (`walk_ik`): keypoints reached, limits kept, parameters matched, a record that says
it has no dynamics, kinematic-only validation, and the environment refusing force/torque inputs."""

import h5py
import mujoco
import numpy as np
import pytest

from opt2skill.tasks.walk_ik import foot_placements
from opt2skill.data.reader import Dataset
from opt2skill.data.record import FRAME_DT
from opt2skill.data.trajfile import read_meta, read_trajectory, write_trajectory
from opt2skill.data.validate import validate
from opt2skill.envs import ReferenceBank, TrackingEnv, tracking_config
from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.trajopt.generate import GenerateRequest, generate
from opt2skill.tasks import get_task


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


@pytest.fixture(scope="module")
def ik(robot):
    return get_task("walk_ik", robot, {"duration": 3.0})


@pytest.fixture(scope="module")
def walk(robot, ik):
    params = dict(ik.param_space().sample(0, 3), speed=1.0, clearance=0.15)
    return ik.solve(params, seed=0)


def test_ik_frames_reach_their_keypoints_within_5_mm_and_keep_joint_limits(robot, ik, walk):
    gait, feet = ik.gait(walk.params)
    ee = list(walk.ee_names)
    worst = 0.0
    for k, t in enumerate(walk.time):
        placements, _ = foot_placements(gait, feet, float(t), walk.params["clearance"])
        for foot, (position, _) in placements.items():
            worst = max(worst, float(np.linalg.norm(walk.ee_pos[k, ee.index(foot)] - position)))
    assert worst < 0.005, worst
    m = robot.mj_model
    for j in range(1, m.njnt):  # every hinge joint within its MJCF range
        q = walk.qpos[:, m.jnt_qposadr[j]]
        lo, hi = m.jnt_range[j]
        assert q.min() >= lo - 1e-6 and q.max() <= hi + 1e-6, mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
    # the walk walks: the base covers about speed x cruise time, and both feet left the ground
    assert walk.qpos[-1, 0] - walk.qpos[0, 0] > 0.3
    assert (~walk.contact_active).any(axis=0).all()


def test_velocities_are_finite_differences_of_the_positions(robot, walk):
    q = walk.qpos
    v = np.zeros(robot.mj_model.nv)
    mujoco.mj_differentiatePos(robot.mj_model, v, 2 * FRAME_DT, q[99], q[101])
    assert np.allclose(walk.qvel[100], v)
    assert not walk.joint_torque.any() and not walk.contact_wrench.any()


def test_ik_and_to_walks_of_the_same_seed_and_index_share_their_parameters(robot):
    to, ik = get_task("walk", robot), get_task("walk_ik", robot)
    for seed, index in ((0, 0), (0, 17), (3, 5)):
        assert ik.param_space().sample(seed, index) == to.param_space().sample(seed, index)
    ranges = {"ranges": {"speed": (0.5, 1.0)}}
    to, ik = get_task("walk", robot, ranges), get_task("walk_ik", robot, ranges)
    assert ik.param_space().sample(1, 2) == to.param_space().sample(1, 2)
    # and the same keypoints: footholds and timing of the gait plan
    params = to.param_space().sample(1, 2)
    (g_to, _), (g_ik, _) = to.gait(params), ik.gait(params)
    assert [(s.liftoff, s.touchdown) for s in g_to.steps] == [(s.liftoff, s.touchdown) for s in g_ik.steps]
    assert all(np.array_equal(a.target.position, b.target.position) for a, b in zip(g_to.steps, g_ik.steps))


def test_the_record_says_it_has_no_dynamics_and_old_files_read_as_to(walk, tmp_path):
    path = tmp_path / "000000.h5"
    write_trajectory(path, walk, 0)
    back = read_trajectory(path)
    assert (back.source, back.has_dynamics) == ("ik", False)
    assert (read_meta(path).source, read_meta(path).has_dynamics) == ("ik", False)
    with h5py.File(path, "r+") as f:  # a file written before the attributes existed
        del f["traj_000000"].attrs["source"], f["traj_000000"].attrs["has_dynamics"]
    old = read_trajectory(path)
    assert (old.source, old.has_dynamics) == ("to", True)


def test_validation_is_kinematic_only_and_says_so(robot, ik, walk):
    v = validate(robot, walk, task_errors=ik.task_errors(walk))
    assert v["accepted"], v["reasons"]
    assert v["kinematic_only"] and "dynamics and replay checks skipped" in v["note"]
    assert {"dynamic_gap", "id_residual_frames_max", "friction_violation", "replay_fallen_windows"} <= set(v["skipped"])
    assert {"joint_limit_violation", "foot_slip", "foot_penetration", "task.speed_error"} <= set(v["figures"])
    assert "dynamic_gap" not in v["figures"]


def test_the_environment_refuses_force_and_torque_inputs_for_kinematic_references(robot, walk):
    bank = ReferenceBank.from_trajectories(robot, [walk], tracking_config("walk_ik").observations.end_effectors)
    assert not bank.has_dynamics and bank.source == "ik"
    for ablation in ("pos_f", "pos_t", "pos_f_t"):
        with pytest.raises(ConfigError, match="--ablation pos"):
            TrackingEnv(robot, bank, tracking_config("walk_ik", ablation), 1)


def test_generate_walk_ik_writes_a_validated_dataset(tmp_path):
    out = tmp_path / "ik"
    summary = generate(GenerateRequest(task="walk_ik", n=1, seed=0, out=out, workers=1), progress=False)
    assert summary["done"] == 1
    ds = Dataset.open(out, "accepted") if summary["counts"]["accepted"] else Dataset.open(out, "rejected")
    meta = ds.meta(0)
    assert (meta.source, meta.has_dynamics, meta.task) == ("ik", False, "walk_ik")
    assert meta.validation["kinematic_only"]
    assert meta.params == get_task("walk", load_robot("digit")).param_space().sample(0, 0)
