"""MuJoCo and Pinocchio describe the same robot: kinematics and dynamics agree to 1e-9."""

import numpy as np
import pytest

from opt2skill.model import load_robot
from opt2skill.model.check import compare, random_states
from opt2skill.model.convert import (
    qacc_mj_to_pin,
    qacc_pin_to_mj,
    qpos_mj_to_pin,
    qpos_pin_to_mj,
    qvel_mj_to_pin,
    qvel_pin_to_mj,
)

TOL = 1e-9
N_SAMPLES = 25


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


def samples(robot):
    return random_states(robot, N_SAMPLES, seed=1234)


def test_conversions_round_trip(robot):
    for qpos, qvel in samples(robot):
        q = qpos_mj_to_pin(qpos)
        assert np.allclose(qpos_pin_to_mj(q), qpos, atol=1e-15)
        v = qvel_mj_to_pin(qpos, qvel)
        assert np.allclose(qvel_pin_to_mj(qpos, v), qvel, atol=1e-12)
        a = np.random.default_rng(0).normal(size=robot.nv)
        assert np.allclose(qacc_mj_to_pin(qpos, qvel, qacc_pin_to_mj(qpos, v, a)), a, atol=1e-12)


def test_batched_conversions_match_single(robot):
    states = list(samples(robot))
    qpos = np.stack([s[0] for s in states])
    qvel = np.stack([s[1] for s in states])
    batched = qvel_mj_to_pin(qpos, qvel)
    for i in range(len(states)):
        assert np.allclose(batched[i], qvel_mj_to_pin(qpos[i], qvel[i]), atol=1e-15)


@pytest.fixture(scope="module")
def agreement(robot):
    return compare(robot, n=N_SAMPLES, seed=1234)


@pytest.mark.parametrize("quantity", ["site_position", "site_rotation", "mass_matrix", "gravity", "bias", "jacobian"])
def test_mujoco_and_pinocchio_agree(agreement, quantity):
    assert getattr(agreement, quantity) < TOL, (quantity, getattr(agreement, quantity))


def test_agreement_exercises_velocity_terms(agreement):
    # The random velocities make Coriolis terms of tens of N m: a frame-convention bug would show.
    assert agreement.largest_coriolis > 1.0


def test_comparison_detects_a_wrong_model(robot):
    """The check is not vacuous: an armature missing from Pinocchio is caught."""
    import copy

    broken = copy.copy(robot)
    broken.pin_model = robot.pin_model.copy()
    armature = broken.pin_model.armature.copy()
    armature[9] = 0.0  # left knee (0.2792)
    broken.pin_model.armature = armature
    assert compare(broken, n=3, seed=0).mass_matrix > 0.1


def test_joint_limits_and_order_agree(robot):
    pm, m, cfg = robot.pin_model, robot.mj_model, robot.config
    assert list(pm.names)[2:] == cfg.joint_names == [m.joint(i).name for i in range(1, m.njnt)]
    assert [m.actuator(i).name for i in range(m.nu)] == cfg.joint_names
    assert np.array_equal(pm.lowerPositionLimit[7:], m.jnt_range[1:, 0])
    assert np.array_equal(pm.upperPositionLimit[7:], m.jnt_range[1:, 1])
    assert np.array_equal(pm.effortLimit[6:], cfg.torque_limit)
    assert np.array_equal(pm.velocityLimit[6:], cfg.velocity_limit)
    assert np.array_equal(m.actuator_forcerange[:, 1], cfg.torque_limit)
    assert np.array_equal(m.actuator_gainprm[:, 0], cfg.kp)
    assert np.array_equal(-m.actuator_biasprm[:, 2], cfg.kd)
    assert np.allclose(pm.gravity.linear, m.opt.gravity)


def test_mass_matches_figures(robot):
    mass_mj = robot.mj_model.body_mass.sum()
    mass_pin = sum(inertia.mass for inertia in robot.pin_model.inertias)
    assert abs(mass_mj - 47.925414) < 1e-6
    assert abs(mass_pin - mass_mj) < 1e-9
