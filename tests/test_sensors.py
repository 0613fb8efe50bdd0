"""The sensors a policy reads decode to the quantities they claim to measure."""

import mujoco
import numpy as np
import pytest

from opt2skill.geometry import rotate_inv
from opt2skill.model import load_robot
from opt2skill.model.sensors import SensorLayout
from opt2skill.model.statics import gravity_compensation


@pytest.fixture(scope="module")
def pushed():
    """Digit standing under gravity feedforward, pushed sideways and forward for 0.15 s."""
    robot = load_robot("digit")
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = robot.stand_qpos
    d.ctrl[:] = gravity_compensation(robot, robot.stand_qpos).torque / robot.config.kp
    d.qvel[0], d.qvel[1] = 0.1, 0.15
    for _ in range(150):
        mujoco.mj_step(m, d)
    # mj_step evaluates sensors before it integrates: sensordata lags qpos by one step until mj_forward.
    mujoco.mj_forward(m, d)
    return robot, m, d


def manual_foot_wrench(m, d, body_id, about):
    """Sum of mj_contactForce over the foot's contacts: force on the foot, torque about `about`."""
    force, torque = np.zeros(3), np.zeros(3)
    for i in range(d.ncon):
        c = d.contact[i]
        b1, b2 = m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]
        if body_id not in (b1, b2):
            continue
        local = np.zeros(6)
        mujoco.mj_contactForce(m, d, i, local)
        f = c.frame.reshape(3, 3).T @ local[:3]  # force of geom1 on geom2, world axes
        f = -f if b1 == body_id else f
        force += f
        torque += np.cross(c.pos - about, f)
    return np.concatenate([force, torque])


def test_contact_wrench_matches_summed_contact_forces(pushed):
    robot, m, d = pushed
    layout = SensorLayout.from_model(m, robot.config)
    soles = np.stack([d.site_xpos[robot.site_id(f.sole_site)] for f in robot.config.feet])
    wrench = layout.contact_wrench(d.sensordata, soles)
    for k, foot in enumerate(robot.config.feet):
        body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, foot.body)
        expected = manual_foot_wrench(m, d, body, soles[k])
        assert np.abs(wrench[k] - expected).max() < 1e-8
        assert np.abs(expected[3:5]).max() > 1.0  # the push makes real contact moments
    assert np.all(layout.contact_found(d.sensordata) >= 1)


def test_batched_decoding_matches_single(pushed):
    robot, m, d = pushed
    layout = SensorLayout.from_model(m, robot.config)
    batch = np.stack([d.sensordata, 2 * d.sensordata])
    about = np.zeros((2, 2, 3))
    assert np.allclose(layout.contact_wrench(batch, about)[0], layout.contact_wrench(d.sensordata, about[0]))


def test_joint_imu_and_end_effector_sensors(pushed):
    robot, m, d = pushed
    layout = SensorLayout.from_model(m, robot.config)
    s = d.sensordata
    assert np.allclose(s[layout.joint_pos], d.qpos[7:]) and np.allclose(s[layout.joint_vel], d.qvel[6:])
    assert np.allclose(s[layout.joint_torque], d.actuator_force)
    assert np.allclose(s[layout.imu_quat], d.qpos[3:7]) and np.allclose(s[layout.imu_gyro], d.qvel[3:6])
    # The IMU sits at the base origin, so its velocimeter reads the base velocity in the body frame.
    assert np.allclose(s[layout.imu_linvel], rotate_inv(d.qpos[3:7], d.qvel[:3]))
    for k, name in enumerate(layout.ee_names):
        assert np.allclose(s[layout.ee_pos[k]], d.site_xpos[robot.site_id(robot.config.end_effectors[name])])
