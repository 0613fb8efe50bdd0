"""Contacts beyond the feet (issue 15): a dataset whose contacts include the hands sizes the
observations, the reward's contact-force term, the ONNX metadata and the 2 kHz player's observations
by its contact names; MuJoCo measures the hands' contact forces; a policy trained on one contact set
refuses references with another, naming both.

The references are squats recorded from the simulator (envs.recorded), stored once with the feet as
contacts and once with the feet and hands, the hands in the air (zero force, inactive), written with
the normal data store."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest
from envs_support import ROBOT, exact_config
from eval_support import player_matches_environment, write_dataset

from opt2skill.data.reader import Dataset
from opt2skill.data.record import Trajectory, build_trajectory
from opt2skill.deploy.export import export_policy
from opt2skill.deploy.metadata import read_metadata
from opt2skill.deploy.player import Player
from opt2skill.envs import ReferenceBank, TrackingEnv
from opt2skill.envs.recorded import record_reference, squat_targets
from opt2skill.errors import DataError
from opt2skill.eval.evaluate import EvalRequest, evaluate
from opt2skill.model.mujoco_model import build_spec
from opt2skill.model.sensors import SensorLayout
from opt2skill.rl.session import TrainRequest, train

FEET = ("left_foot", "right_foot")
HANDS = ("left_hand", "right_hand")
STEPS = 40  # frames of each recorded squat


def with_contacts(traj: Trajectory, names: tuple[str, ...]) -> Trajectory:
    """`traj` (feet contacts) with the contacts `names`: the feet's wrenches as recorded, every other
    contact in the air (zero wrench, inactive)."""
    wrench = np.zeros((traj.num_frames, len(names), 6))
    active = np.zeros((traj.num_frames, len(names)), dtype=bool)
    for i, name in enumerate(names):
        if name in traj.contact_names:
            wrench[:, i] = traj.contact_wrench[:, traj.contact_names.index(name)]
            active[:, i] = traj.contact_active[:, traj.contact_names.index(name)]
    return build_trajectory(ROBOT, traj.qpos, traj.qvel, traj.joint_torque, wrench, active, task=traj.task,
                            contact_names=names, params=traj.params, seed=traj.seed, ee_names=traj.ee_names)


@pytest.fixture(scope="module")
def squats() -> list[Trajectory]:
    return [dataclasses.replace(record_reference(ROBOT, squat_targets(ROBOT, STEPS, depth=depth)),
                                params={"depth": depth})
            for depth in (0.1, 0.15)]


@pytest.fixture(scope="module")
def datasets(squats, tmp_path_factory) -> tuple:
    root = tmp_path_factory.mktemp("contacts")
    feet = write_dataset(root / "feet", squats)
    hands = write_dataset(root / "hands", [with_contacts(t, FEET + HANDS) for t in squats])
    return feet, hands


@pytest.fixture(scope="module")
def hands_run(datasets, tmp_path_factory) -> tuple:
    """A run trained for two PPO iterations of 4 worlds on the hands dataset, and its exported policy."""
    _, hands = datasets
    run = tmp_path_factory.mktemp("hands_run") / "run"
    train(TrainRequest(dataset=hands, out=run, steps=4 * 48 * 2, num_envs=4, threads=1, checkpoint_every=1))
    path, meta = export_policy(run, run.parent / "policy.onnx")
    return run, path, meta


def test_observations_grow_by_three_per_point_contact_and_read_the_hands_forces(squats):
    config = exact_config()
    hands = [with_contacts(t, FEET + HANDS) for t in squats]
    envs = [TrackingEnv(ROBOT, ReferenceBank.from_trajectories(ROBOT, refs, config.observations.end_effectors),
                        config, 2, seed=0, threads=1) for refs in (squats, hands)]
    feet_env, hands_env = envs
    try:
        assert hands_env.actor_dim == feet_env.actor_dim + 6  # ref_contact_force: 3 per hand
        assert hands_env.critic_dim == feet_env.critic_dim + 12  # contact_force and ref_contact_force
        lay = hands_env.layout
        assert lay.critic["contact_force"].stop - lay.critic["contact_force"].start == 12
        assert lay.actor["ref_contact_force"].stop - lay.actor["ref_contact_force"].start == 12
        for env in envs:
            env.reset_worlds(np.arange(2), np.arange(2), np.zeros(2, dtype=np.int64))
        targets = squat_targets(ROBOT, 10)
        for t in range(10):
            actions = feet_env.actions_for_targets(np.tile(targets[t], (2, 1)))
            a, b = feet_env.step(actions), hands_env.step(actions)
            measured = b.critic[:, lay.critic["contact_force"]].reshape(2, 4, 3)
            # the feet read what the feet-only environment reads; the hands what MuJoCo measures on them
            assert np.array_equal(measured[:, :2], a.critic[:, feet_env.layout.critic["contact_force"]].reshape(2, 2, 3))
            point = hands_env.state.point_force_mean  # (N, npoint, 3): hands and elbows
            names = SensorLayout.from_model(ROBOT.mj_model, ROBOT.config).point_names
            hand_forces = point[:, [names.index(h) for h in HANDS]]
            assert np.all(hand_forces == 0.0) and np.all(measured[:, 2:] == 0.0)  # in the air: nothing touches
            assert measured[:, :2, 2].sum() > 300  # the feet carry the robot
            reference = b.critic[:, lay.critic["ref_contact_force"]].reshape(2, 4, 3)
            assert np.all(reference[:, 2:] == 0) and np.all(reference[:, :2, 2] > 0)
            # the reward's contact-force term compares all four contacts; zero hand forces cost nothing
            assert np.allclose(a.terms["contact_force"], b.terms["contact_force"], rtol=1e-6, atol=1e-9)
    finally:
        for env in envs:
            env.close()


def test_mujoco_measures_the_force_under_a_hand():
    """A box under the left hand: the sensors give the sum of the hand's contact forces (world axes, on
    the hand: upward), the other point contacts read zero, and an elbow's geoms are its two links."""
    spec = build_spec(ROBOT.config)
    model0 = spec.copy().compile()
    data0 = mujoco.MjData(model0)
    data0.qpos[:] = ROBOT.stand_qpos
    mujoco.mj_kinematics(model0, data0)
    hand = data0.site_xpos[mujoco.mj_name2id(model0, mujoco.mjtObj.mjOBJ_SITE, "left_hand")].copy()
    spec.worldbody.add_geom(name="box", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.1, 0.1, 0.05],
                            pos=[hand[0], hand[1], hand[2] - 0.04 - 0.05 + 0.005], contype=3, conaffinity=1)
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[:] = ROBOT.stand_qpos
    mujoco.mj_forward(model, data)
    layout = SensorLayout.from_model(model, ROBOT.config)
    assert layout.point_geoms[layout.point_names.index("left_elbow")] == ("left_shoulder_yaw_link", "left_forearm")
    force = layout.point_force(data.sensordata)
    geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "left_hand")
    expected, f6 = np.zeros(3), np.zeros(6)
    for i in range(data.ncon):
        c = data.contact[i]
        if geom in (c.geom1, c.geom2):
            mujoco.mj_contactForce(model, data, i, f6)
            world = c.frame.reshape(3, 3).T @ f6[:3]  # on geom2
            expected += world if c.geom2 == geom else -world
    left = layout.point_names.index("left_hand")
    assert expected[2] > 1.0  # the box pushes the hand up
    assert np.allclose(force[left], expected, rtol=1e-9, atol=1e-9)
    assert np.all(np.delete(force, left, axis=0) == 0)
    assert layout.point_found(data.sensordata)[left] >= 1


def test_a_hands_dataset_trains_evaluates_and_exports_its_contacts(hands_run, datasets):
    run, path, meta = hands_run
    assert meta.contacts == list(FEET + HANDS)
    assert read_metadata(path).contacts == list(FEET + HANDS)
    terms = {t.name: t.size for t in meta.terms}
    assert terms["ref_contact_force"] == 12
    report, rollouts = evaluate(EvalRequest(run=run, split="all", n=2, threads=1), progress=False)
    assert len(report.results) == 2
    assert rollouts[0].tracked.contact_names == FEET + HANDS
    assert rollouts[0].tracked.contact_wrench.shape[1:] == (4, 6)
    assert np.isfinite(report.results[0].errors.E_force)


def test_the_players_observations_equal_the_environments_on_a_hands_dataset(hands_run, datasets):
    run, path, _ = hands_run
    reference = Dataset.open(datasets[1])[1]
    assert reference.contact_names == FEET + HANDS
    assert player_matches_environment(run, path, reference) < 1e-6


def test_a_policy_refuses_references_with_other_contacts_naming_both(hands_run, datasets):
    run, path, _ = hands_run
    feet, _ = datasets
    both = r"\['left_foot', 'right_foot'\].*\['left_foot', 'right_foot', 'left_hand', 'right_hand'\]"
    with pytest.raises(DataError, match=both):
        evaluate(EvalRequest(run=run, dataset=feet, split="all", n=1, threads=1), progress=False)
    with pytest.raises(DataError, match=both):
        Player(path).run(Dataset.open(feet)[0])
