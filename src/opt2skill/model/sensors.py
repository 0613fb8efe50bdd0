"""Where each sensor lives in `sensordata`, and decoding of batched sensor arrays.

All functions take `sensordata` with any leading dimensions (worlds, time), so the batched
simulator and single-world tools decode the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from opt2skill.model.mujoco_model import sensor_slice
from opt2skill.robots import RobotConfig


@dataclass(frozen=True)
class SensorLayout:
    """Index arrays into `sensordata` for each named group of sensors (see docs/model.md)."""

    imu_quat: np.ndarray  # (4,) w, x, y, z of the IMU site in the world
    imu_gyro: np.ndarray  # (3,) angular velocity, IMU frame
    imu_linvel: np.ndarray  # (3,) linear velocity, IMU frame
    imu_acc: np.ndarray  # (3,) proper acceleration, IMU frame
    joint_pos: np.ndarray  # (nu,)
    joint_vel: np.ndarray  # (nu,)
    joint_torque: np.ndarray  # (nu,) actuator torque actually applied (after clipping)
    ee_pos: np.ndarray  # (nee, 3) world positions of the config's end-effector sites
    contact: np.ndarray  # (nfeet, 10): found, force (3), torque (3), point (3) as MuJoCo reports them
    ee_names: tuple[str, ...]
    foot_names: tuple[str, ...]

    @classmethod
    def from_model(cls, model: mujoco.MjModel, config: RobotConfig) -> SensorLayout:
        def idx(name: str) -> np.ndarray:
            s = sensor_slice(model, name)
            return np.arange(s.start, s.stop)

        return cls(
            imu_quat=idx("imu_quat"),
            imu_gyro=idx("imu_gyro"),
            imu_linvel=idx("imu_linvel"),
            imu_acc=idx("imu_acc"),
            joint_pos=np.concatenate([idx(f"q_{j}") for j in config.joint_names]),
            joint_vel=np.concatenate([idx(f"qd_{j}") for j in config.joint_names]),
            joint_torque=np.concatenate([idx(f"tau_{j}") for j in config.joint_names]),
            ee_pos=np.stack([idx(f"ee_{name}") for name in config.end_effectors]),
            contact=np.stack([idx(f"contact_{f.name}") for f in config.feet]),
            ee_names=tuple(config.end_effectors),
            foot_names=tuple(f.name for f in config.feet),
        )

    def contact_wrench(self, sensordata: np.ndarray, about: np.ndarray) -> np.ndarray:
        """Contact wrench ON each foot, world axes, torque about the points `about` (..., nfeet, 3).

        MuJoCo's net-force contact sensor reports the force the foot exerts on the ground and a
        torque about its own force-weighted contact point; this flips and moves them.
        """
        raw = sensordata[..., self.contact]
        force_on_ground, torque, point = raw[..., 1:4], raw[..., 4:7], raw[..., 7:10]
        force = -force_on_ground
        torque_about = -torque - np.cross(point - about, force_on_ground)
        return np.concatenate([force, torque_about], axis=-1)

    def contact_found(self, sensordata: np.ndarray) -> np.ndarray:
        """Number of contact points of each foot (0 means the foot is in the air)."""
        return sensordata[..., self.contact[:, 0]]
