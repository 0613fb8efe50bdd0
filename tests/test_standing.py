"""PD at the default pose plus gravity feedforward (Pinocchio, feet in contact) holds Digit up."""

import numpy as np
import pytest

from opt2skill.model import load_robot
from opt2skill.model.standing import simulate_standing
from opt2skill.model.statics import gravity_compensation


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


def test_gravity_compensation_balances_the_robot(robot):
    balance = gravity_compensation(robot, robot.stand_qpos)
    assert balance.residual < 1e-9
    weight = robot.mj_model.body_mass.sum() * 9.81
    assert abs(balance.wrenches[:, 2].sum() - weight) < 1e-6
    # Symmetric stance: each foot carries half the weight; torques within limits.
    assert abs(balance.wrenches[0, 2] - balance.wrenches[1, 2]) < 0.01 * weight
    assert np.all(np.abs(balance.torque) < robot.config.torque_limit)
    # Centre of pressure under each sole.
    for foot, wrench in zip(robot.config.feet, balance.wrenches):
        cop_x, cop_y = -wrench[4] / wrench[2], wrench[3] / wrench[2]
        assert abs(cop_x) < foot.half_length and abs(cop_y) < foot.half_width


def test_digit_stands_for_five_seconds(robot):
    report = simulate_standing(robot, seconds=5.0)
    assert not report.fell
    assert report.max_tilt_deg < 2.0
    assert report.max_base_drift_m < 0.01
    assert report.max_foot_slip_m < 0.005
    assert report.max_torque_ratio < 1.0


def test_without_feedforward_the_robot_falls(robot):
    """The feedforward is doing the work: the test above would fail without it."""
    assert simulate_standing(robot, seconds=5.0, feedforward=False).fell
