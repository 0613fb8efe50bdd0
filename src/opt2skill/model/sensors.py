"""Where each sensor lives in `sensordata`, and decoding of batched sensor arrays.

All functions take `sensordata` with any leading dimensions (worlds, time), so the batched
simulator and single-world tools decode the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import cached_property

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
    sole_pos: np.ndarray  # (nfeet, 3) world positions of the feet's sole sites
    ee_vel: np.ndarray  # (nee, 3) world linear velocities of the end-effector sites
    ee_acc: np.ndarray  # (nee, 3) their linear accelerations minus gravity (MuJoCo's framelinacc), world
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
            sole_pos=np.stack([idx(f"sole_{f.name}") for f in config.feet]),
            ee_vel=np.stack([idx(f"eevel_{name}") for name in config.end_effectors]),
            ee_acc=np.stack([idx(f"eeacc_{name}") for name in config.end_effectors]),
            ee_names=tuple(config.end_effectors),
            foot_names=tuple(f.name for f in config.feet),
        )

    def take(self, sensordata: np.ndarray, group: str) -> np.ndarray:
        """`sensordata[..., index]` of a group (e.g. "joint_torque"): a view when the group's sensors
        are one contiguous run, as the loader adds them, which saves the batched simulator a copy."""
        index = getattr(self, group)
        run = self._runs.get(group)
        if run is None:
            return sensordata[..., index]
        return sensordata[..., run].reshape(sensordata.shape[:-1] + index.shape)

    @cached_property
    def _runs(self) -> dict[str, slice]:
        """The groups whose indices are one contiguous run, as slices."""
        runs = {}
        for f in fields(self):
            index = getattr(self, f.name)
            if isinstance(index, np.ndarray) and index.size:
                flat = index.ravel()
                if np.array_equal(flat, np.arange(flat[0], flat[0] + flat.size)):
                    runs[f.name] = slice(int(flat[0]), int(flat[0]) + flat.size)
        return runs

    def contact_wrench(self, sensordata: np.ndarray, about: np.ndarray) -> np.ndarray:
        """Contact wrench ON each foot, world axes, torque about the points `about` (..., nfeet, 3).

        MuJoCo's net-force contact sensor reports the force the foot exerts on the ground and a
        torque about its own force-weighted contact point; this flips and moves them.
        """
        raw = self.take(sensordata, "contact")
        fx, fy, fz = raw[..., 1], raw[..., 2], raw[..., 3]  # force on the ground
        r = raw[..., 7:10] - about
        rx, ry, rz = r[..., 0], r[..., 1], r[..., 2]
        out = np.empty(raw.shape[:-1] + (6,))
        out[..., :3] = -raw[..., 1:4]
        # torque about `about` = -torque - r x force_on_ground, written out (np.cross is slow on small arrays)
        out[..., 3] = rz * fy - ry * fz - raw[..., 4]
        out[..., 4] = rx * fz - rz * fx - raw[..., 5]
        out[..., 5] = ry * fx - rx * fy - raw[..., 6]
        return out

    def contact_found(self, sensordata: np.ndarray) -> np.ndarray:
        """Number of contact points of each foot (0 means the foot is in the air)."""
        return sensordata[..., self.contact[:, 0]]
