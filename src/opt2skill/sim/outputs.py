"""Batched outputs of a policy step from MuJoCo's states and sensor readings.

`mj_step` evaluates sensors before it integrates, so the readings of physics step k describe the
state at its start and the forces acting during it. Quantities of the post-step state therefore
come from the state itself (base, IMU orientation and velocities, joints); forces come from the
readings (the last step's, and the mean over the policy step); end-effector positions are read at
the start of the last step and carried to its end as MuJoCo's semi-implicit Euler step moves them,
p + dt v + dt^2 a (error below 0.05 mm even for violent motions, tests/test_sim_step.py).
"""

from __future__ import annotations

import mujoco
import numpy as np

from opt2skill.errors import ModelError
from opt2skill.geometry import quat_mul, quat_to_mat
from opt2skill.model.robot import Robot
from opt2skill.model.sensors import SensorLayout
from opt2skill.sim.base import SimStep

BASE_QPOS, BASE_QVEL = 7, 6  # the free joint's share of qpos and qvel (docs/conventions.md)


class OutputDecoder:
    def __init__(self, robot: Robot, model: mujoco.MjModel):
        self.layout = SensorLayout.from_model(model, robot.config)
        sid = robot.site_id(robot.config.imu_site)
        if model.site_bodyid[sid] != model.jnt_bodyid[0]:
            raise ModelError(f"sim needs the IMU site '{robot.config.imu_site}' on the floating base body")
        # The IMU is fixed to the base: its readings follow from the base state and its mounting.
        self.imu_pos = model.site_pos[sid].copy()
        self.imu_quat = model.site_quat[sid].copy()
        self.imu_rot = quat_to_mat(self.imu_quat)  # IMU frame -> base frame
        self.imu_at_base = bool(np.allclose(self.imu_pos, 0.0) and np.allclose(self.imu_quat, [1, 0, 0, 0]))

    def decode(
        self,
        time: np.ndarray,
        qpos: np.ndarray,
        qvel: np.ndarray,
        qvel_start: np.ndarray,
        sensordata: np.ndarray,
        dt: float,
        duration: float,
        gravity: np.ndarray,
        prop_pose: np.ndarray | None = None,
        prop_vel: np.ndarray | None = None,
    ) -> SimStep:
        """Outputs from the post-step state and the readings (N, S, nsensordata) of the S physics steps.

        `dt` carries end-effector positions from the start of the last step to the state's instant
        (the physics step, or 0 when the readings were taken at that state); `duration` is the
        policy step (for the mean joint acceleration); `gravity` (N, 3) each world's gravity
        (MuJoCo's frame accelerations exclude it); `prop_pose` (N, nfree, 7) and `prop_vel`
        (N, nfree, 6) the free props' state (none by default). `qpos`, `qvel`: the robot's only.
        """
        lay = self.layout
        quat, w_body = qpos[:, 3:7], qvel[:, 3:6]
        v_body = _rotate_inv(quat, qvel[:, :3])
        if self.imu_at_base:
            imu_quat, gyro, linvel = quat.copy(), w_body.copy(), v_body
        else:
            imu_quat = quat_mul(quat, self.imu_quat)
            gyro = w_body @ self.imu_rot
            linvel = (v_body + np.cross(w_body, self.imu_pos)) @ self.imu_rot
        last = sensordata[:, -1]  # views into the caller's buffer below: every output is computed or copied
        wrench = lay.contact_wrench(sensordata, lay.take(sensordata, "sole_pos"))  # (N, S, nfeet, 6)
        torque = lay.take(sensordata, "joint_torque")
        point = lay.point_force(sensordata)  # (N, S, npoint, 3)
        ee_acc = lay.take(last, "ee_acc") + gravity[:, None]  # framelinacc excludes gravity
        joint_vel = qvel[:, BASE_QVEL:]
        return SimStep(
            time=time,
            qpos=qpos,
            qvel=qvel,
            imu_quat=imu_quat,
            imu_gyro=gyro,
            imu_linvel=linvel,
            imu_acc=lay.take(last, "imu_acc").copy(),
            joint_pos=qpos[:, BASE_QPOS:],
            joint_vel=joint_vel,
            joint_acc=(joint_vel - qvel_start[:, BASE_QVEL:]) / duration,
            torque=torque[:, -1].copy(),
            torque_mean=torque.sum(axis=1) / torque.shape[1],  # sum / n: ndarray.mean costs more here
            ee_pos=lay.take(last, "ee_pos") + dt * lay.take(last, "ee_vel") + dt * dt * ee_acc,
            contact_wrench=wrench[:, -1],
            contact_wrench_mean=wrench.sum(axis=1) / wrench.shape[1],
            contact_found=lay.contact_found(last),
            point_force=point[:, -1],
            point_force_mean=point.sum(axis=1) / point.shape[1],
            point_found=lay.point_found(last),
            unstable=np.zeros(len(time), dtype=bool),
            prop_pose=np.zeros((len(time), 0, 7)) if prop_pose is None else prop_pose,
            prop_vel=np.zeros((len(time), 0, 6)) if prop_vel is None else prop_vel,
        )


_NEXT, _PREV = np.array([1, 2, 0]), np.array([2, 0, 1])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (N, 3) arrays (np.cross costs more on small arrays)."""
    return a[:, _NEXT] * b[:, _PREV] - a[:, _PREV] * b[:, _NEXT]


def _rotate_inv(quat: np.ndarray, v: np.ndarray) -> np.ndarray:
    """v (N, 3) from world to body by unit quaternions (N, 4): geometry.rotate_inv without building
    N rotation matrices, since it runs every step."""
    w, u = quat[:, :1], -quat[:, 1:]  # the conjugate rotates world to body
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)
