"""Where each sensor lives in `sensordata`, and decoding of batched sensor arrays.

All functions take `sensordata` with any leading dimensions (worlds, time), so the batched
simulator and single-world tools decode the same way.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from functools import cached_property

import mujoco
import numpy as np

from opt2skill.errors import DataError
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
    point_contact: np.ndarray  # (nsensor, 4): found, force (3) on each geom of a point contact
    point_sum: np.ndarray  # (npoint, nsensor) 1 where a sensor's geom belongs to a point contact
    ee_names: tuple[str, ...]
    foot_names: tuple[str, ...]
    point_names: tuple[str, ...]  # end effectors that are not feet (hands, elbows), config order
    point_geoms: tuple[tuple[str, ...], ...]  # the geoms each one's contacts are measured on

    @classmethod
    def from_model(cls, model: mujoco.MjModel, config: RobotConfig) -> SensorLayout:
        def idx(name: str) -> np.ndarray:
            s = sensor_slice(model, name)
            return np.arange(s.start, s.stop)

        feet = [f.name for f in config.feet]
        points = tuple(name for name in config.end_effectors if name not in feet)
        sensors, owner, geoms = [], [], []
        for i, name in enumerate(points):
            mine = []
            while (sid := mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, f"pcontact_{name}_{len(mine)}")) >= 0:
                mine.append(model.geom(int(model.sensor_objid[sid])).name)
                sensors.append(idx(f"pcontact_{name}_{len(mine) - 1}"))
                owner.append(i)
            geoms.append(tuple(mine))
        point_sum = np.zeros((len(points), len(sensors)))
        point_sum[owner, np.arange(len(sensors))] = 1.0
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
            point_contact=np.stack(sensors) if sensors else np.zeros((0, 4), dtype=np.int64),
            point_sum=point_sum,
            ee_names=tuple(config.end_effectors),
            foot_names=tuple(feet),
            point_names=points,
            point_geoms=tuple(geoms),
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
            if isinstance(index, np.ndarray) and index.size and f.name != "point_sum":
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

    def point_force(self, sensordata: np.ndarray) -> np.ndarray:
        """Contact force ON each point-contact end effector (..., npoint, 3), world axes: the sum over
        its geoms, sign flipped as for the feet (MuJoCo reports the force the geom exerts)."""
        raw = self.take(sensordata, "point_contact")[..., 1:4]  # (..., nsensor, 3)
        return -np.einsum("ps,...sc->...pc", self.point_sum, raw)

    def point_found(self, sensordata: np.ndarray) -> np.ndarray:
        """Number of contact points of each point-contact end effector (..., npoint)."""
        return self.take(sensordata, "point_contact")[..., 0] @ self.point_sum.T

    @property
    def contact_names(self) -> tuple[str, ...]:
        """Every end effector whose contacts are measured: the feet (6D), then the point contacts (3D)."""
        return self.foot_names + self.point_names

    def contact_rows(self, names: Sequence[str]) -> np.ndarray:
        """Rows of `names` in `contact_names` (the order of `contact_wrenches`' stacked input)."""
        unknown = [n for n in names if n not in self.contact_names]
        if unknown:
            raise DataError(f"contacts {unknown} are not end effectors of the robot (its contacts can be "
                            f"{list(self.contact_names)})")
        unmeasured = [n for n in names if n in self.point_names and not self.point_geoms[self.point_names.index(n)]]
        if unmeasured:
            raise DataError(f"no collision geom of the robot's model holds the site of {unmeasured}: contact forces "
                            "there cannot be measured")
        return np.array([self.contact_names.index(n) for n in names], dtype=np.int64)


def contact_wrenches(foot_wrench: np.ndarray, point_force: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Wrenches (..., k, 6) of the contacts `rows` (`SensorLayout.contact_rows`): a foot's as measured
    (about its sole site), a point contact's force with a zero torque (the record's convention)."""
    point = np.concatenate([point_force, np.zeros_like(point_force)], axis=-1)
    return np.concatenate([foot_wrench, point], axis=-2)[..., rows, :]
