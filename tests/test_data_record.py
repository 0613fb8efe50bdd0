"""The record's derived fields match MuJoCo on a real simulated motion."""

import mujoco
import numpy as np

from opt2skill.data.record import FRAME_DT, build_trajectory
from opt2skill.geometry import quat_to_mat
from opt2skill.model import load_robot
from opt2skill.model.sensors import SensorLayout
from opt2skill.model.statics import gravity_compensation


def test_build_trajectory_from_a_pushed_stand():
    robot = load_robot("digit")
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = robot.stand_qpos
    d.qvel[0], d.qvel[5] = 0.2, 0.5  # forward and yawing
    d.ctrl[:] = gravity_compensation(robot, robot.stand_qpos).torque / robot.config.kp
    layout = SensorLayout.from_model(m, robot.config)
    soles = [robot.site_id(f.sole_site) for f in robot.config.feet]
    qpos, qvel, tau, wrench = [], [], [], []
    for _ in range(40):  # 0.2 s at 200 Hz
        mujoco.mj_forward(m, d)
        qpos.append(d.qpos.copy()), qvel.append(d.qvel.copy()), tau.append(d.actuator_force.copy())
        wrench.append(layout.contact_wrench(d.sensordata, d.site_xpos[soles]))
        for _ in range(5):
            mujoco.mj_step(m, d)
    traj = build_trajectory(
        robot, np.array(qpos), np.array(qvel), np.array(tau), np.array(wrench),
        np.ones((40, 2), bool), task="stand", contact_names=("left_foot", "right_foot"), params={}, seed=0,
    )
    assert traj.num_frames == 40 and np.allclose(np.diff(traj.time), FRAME_DT)
    R = quat_to_mat(traj.qpos[:, 3:7])
    assert np.allclose(np.einsum("tji,tj->ti", R, traj.qvel[:, :3]), traj.base_lin_vel)
    assert np.abs(traj.base_ang_vel[:, 2]).max() > 0.1
    # ee_pos_base rotated back into the world equals ee_pos, and the feet sit near the ground.
    world = np.einsum("tij,tej->tei", R, traj.ee_pos_base) + traj.qpos[:, None, :3]
    assert np.allclose(world, traj.ee_pos)
    feet = [traj.ee_names.index("left_foot"), traj.ee_names.index("right_foot")]
    assert np.abs(traj.ee_pos[:, feet, 2]).max() < 0.01
    assert abs(traj.com[0, 2] - 0.9839) < 0.002  # the stand pose's centre of mass height
    assert abs(traj.contact_wrench[-1, :, 2].sum() - m.body_mass.sum() * 9.81) < 0.1 * m.body_mass.sum() * 9.81
