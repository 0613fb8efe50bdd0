"""The batched-simulator interface: what any physics backend (C MuJoCo now, MuJoCo Warp later) provides.

A simulator holds N worlds of one robot. Each world has its own physical parameters, action
delay and terrain. One `step(targets)` advances every world by one policy step (S physics steps
with the PD servos at the physics rate) and returns a `SimStep` of batched arrays. The task logic
(`envs`) sees only this interface; docs/sim.md is its full contract.
"""

from __future__ import annotations

import os
from abc import ABC, abstractmethod
from dataclasses import dataclass, fields

import numpy as np

from opt2skill.errors import ConfigError
from opt2skill.model.robot import Robot
from opt2skill.scene.slots import PropSlots
from opt2skill.scene.terrain import Terrain
from opt2skill.sim.params import NominalModel, WorldParams


@dataclass(frozen=True)
class SimConfig:
    """How worlds are stepped. Training: 5 substeps of 1 ms; the 2 kHz player: 10 of 0.5 ms."""

    nsubstep: int = 5  # physics steps per policy step
    physics_dt: float | None = None  # seconds; None keeps the model's timestep (1 ms for Digit)
    max_delay: float = 0.02  # longest action delay a world may be given, seconds
    nthread: int | None = None  # physics threads; None: one per core
    max_speed: float = 100.0  # any |qvel| entry beyond this (m/s, rad/s) flags a world as exploded

    def __post_init__(self) -> None:
        if not (isinstance(self.nsubstep, int) and 1 <= self.nsubstep <= 100):
            raise ConfigError(f"nsubstep must be an integer in [1, 100], got {self.nsubstep}")
        if self.physics_dt is not None and not (1e-5 <= self.physics_dt <= 0.01):
            raise ConfigError(f"physics_dt must be in [1e-5, 0.01] s, got {self.physics_dt}")
        if not (0.0 <= self.max_delay <= 0.2):
            raise ConfigError(f"max_delay must be in [0, 0.2] s, got {self.max_delay}")
        if self.nthread is not None and not (isinstance(self.nthread, int) and self.nthread >= 1):
            raise ConfigError(f"nthread must be a positive integer or None, got {self.nthread}")
        if not (self.max_speed > 0):
            raise ConfigError(f"max_speed must be positive, got {self.max_speed}")

    @property
    def threads(self) -> int:
        return self.nthread or os.cpu_count() or 1


@dataclass
class SimStep:
    """Batched outputs, leading dimension = worlds. Which instant each refers to (docs/sim.md):

    END: the end of the policy step (the post-step state), exact unless noted.
    LAST: the last physics step of the policy step (forces acting during it, evaluated at its start).
    MEAN: the mean over the policy step's physics steps (equal to the impulse / duration).
    """

    time: np.ndarray  # (N,) END, seconds since the world's reset
    qpos: np.ndarray  # (N, nq) END, the robot's MuJoCo layout (props are `prop_pose`)
    qvel: np.ndarray  # (N, nv) END, the robot's MuJoCo layout (base linear velocity in the world frame)
    imu_quat: np.ndarray  # (N, 4) END, IMU orientation in the world, w x y z
    imu_gyro: np.ndarray  # (N, 3) END, angular velocity, IMU frame
    imu_linvel: np.ndarray  # (N, 3) END, linear velocity, IMU frame
    imu_acc: np.ndarray  # (N, 3) LAST, proper acceleration (accelerometer), IMU frame
    joint_pos: np.ndarray  # (N, nu) END
    joint_vel: np.ndarray  # (N, nu) END
    joint_acc: np.ndarray  # (N, nu) MEAN, (joint_vel END - joint_vel at the start) / policy dt
    torque: np.ndarray  # (N, nu) LAST, torque applied by each servo (after clipping)
    torque_mean: np.ndarray  # (N, nu) MEAN
    ee_pos: np.ndarray  # (N, nee, 3) END, world; carried from the LAST step's start by its velocity
    contact_wrench: np.ndarray  # (N, nfeet, 6) LAST, on the foot, world axes, about its sole site
    contact_wrench_mean: np.ndarray  # (N, nfeet, 6) MEAN
    contact_found: np.ndarray  # (N, nfeet) LAST, number of contact points of each foot
    point_force: np.ndarray  # (N, npoint, 3) LAST, contact force on each point-contact end effector (hands,
    #                          elbows: SensorLayout.point_names), world axes
    point_force_mean: np.ndarray  # (N, npoint, 3) MEAN
    point_found: np.ndarray  # (N, npoint) LAST, number of contact points of each
    unstable: np.ndarray  # (N,) bool: the world diverged this step; it was held, reset it
    prop_pose: np.ndarray  # (N, nfree, 7) END, free props' position and quaternion (w x y z), world
    prop_vel: np.ndarray  # (N, nfree, 6) END, their linear (world) and angular (body) velocity

    def rows(self, index: np.ndarray) -> SimStep:
        return SimStep(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def assign(self, index: np.ndarray, other: SimStep) -> None:
        for f in fields(self):
            getattr(self, f.name)[index] = getattr(other, f.name)


class BatchedSim(ABC):
    """N worlds of one robot, stepped together. Worlds are addressed by integer index arrays."""

    robot: Robot
    config: SimConfig
    nworld: int
    nbody: int  # bodies of the model, world included (the length of WorldParams.mass_scale rows)
    nu: int  # actuators = actuated joints
    terrains: tuple[Terrain, ...]  # a world's terrain is WorldParams.terrain, an index into these
    # A world's props are WorldParams.props, an index into `props.sets` (scene/slots.py); a backend
    # without props has the one empty set.
    props: PropSlots = PropSlots()

    @property
    def nsubstep(self) -> int:
        return self.config.nsubstep

    @property
    @abstractmethod
    def physics_dt(self) -> float:
        """Seconds per physics step."""

    @property
    def policy_dt(self) -> float:
        return self.nsubstep * self.physics_dt

    @property
    @abstractmethod
    def params(self) -> WorldParams:
        """Current parameters of all worlds (a copy)."""

    @property
    @abstractmethod
    def z_offset(self) -> np.ndarray:
        """(N,) height added to each world's base at its last reset to stand it on its terrain."""

    @abstractmethod
    def set_params(self, worlds: np.ndarray, params: WorldParams) -> None:
        """Set the parameters of `worlds` (k,) from `params` (k rows), from nominal values."""

    @abstractmethod
    def reset(
        self,
        worlds: np.ndarray,
        qpos: np.ndarray,
        qvel: np.ndarray,
        targets: np.ndarray | None = None,
        params: WorldParams | None = None,
        prop_pose: np.ndarray | None = None,
        prop_vel: np.ndarray | None = None,
    ) -> SimStep:
        """Put `worlds` (k,) in robot states (k, nq), (k, nv), standing on their terrain, and their free
        props at `prop_pose` (k, nfree, 7) with `prop_vel` (k, nfree, 6) (default: their scene poses,
        at rest; lifted with the robot); outputs at that instant."""

    @abstractmethod
    def step(self, targets: np.ndarray) -> SimStep:
        """Advance all worlds one policy step towards PD targets (N, nu) (action + default pose)."""

    @abstractmethod
    def push(self, worlds: np.ndarray, velocity: np.ndarray) -> None:
        """Add `velocity` (k, 3) m/s, world frame, to the base of `worlds` (k,): an external impulse
        on the base, felt from the next step on."""

    @abstractmethod
    def gains(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Effective Kp, Kd and torque limits (N, nu) of every world."""

    @abstractmethod
    def terrain_height(self, xy: np.ndarray) -> np.ndarray:
        """Terrain surface height (N, k) under points xy (N, k, 2), each world on its own terrain."""

    def check_worlds(self, worlds) -> np.ndarray:
        """World indices from an index array or a boolean mask; ConfigError if out of range or repeated."""
        worlds = np.atleast_1d(np.asarray(worlds))
        if worlds.dtype == bool:
            worlds = np.flatnonzero(worlds)
        if worlds.ndim != 1 or not np.issubdtype(worlds.dtype, np.integer):
            raise ConfigError("worlds must be a 1-D array of world indices or a boolean mask")
        if worlds.size and (worlds.min() < 0 or worlds.max() >= self.nworld or len(np.unique(worlds)) != len(worlds)):
            raise ConfigError(f"world indices must be distinct and in [0, {self.nworld - 1}]")
        return worlds

    def close(self) -> None:
        """Release threads and memory."""

    def __enter__(self) -> BatchedSim:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class HostBookkeeping(BatchedSim):
    """What both backends keep on the host: the physics step, each world's parameters and z offset,
    the nominal model (gains), and the checks of reset and step inputs."""

    _dt: float
    _params: WorldParams
    _z_offset: np.ndarray
    _nominal: NominalModel

    @property
    def physics_dt(self) -> float:
        return self._dt

    @property
    def params(self) -> WorldParams:
        return self._params.rows(np.arange(self.nworld))

    @property
    def z_offset(self) -> np.ndarray:
        return self._z_offset.copy()

    def gains(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._nominal.gains(self._params)

    def terrain_height(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=float)
        if xy.ndim != 3 or xy.shape[0] != self.nworld or xy.shape[2] != 2:
            raise ConfigError(f"xy must have shape ({self.nworld}, k, 2), got {xy.shape}")
        out = np.zeros(xy.shape[:2])
        which = self._params.terrain
        for index in np.unique(which):  # a loop over the few terrains, not the worlds
            worlds = which == index
            out[worlds] = self.terrains[index].height(xy[worlds])
        return out

    def checked_reset(self, worlds, qpos, qvel, targets, nq: int, nv: int):
        """(worlds, qpos (k, nq), qvel (k, nv), targets (k, nu) or None), checked."""
        worlds = self.check_worlds(worlds)
        k = len(worlds)
        qpos, qvel = checked_array("qpos", qpos, (k, nq)), checked_array("qvel", qvel, (k, nv))
        return worlds, qpos, qvel, None if targets is None else checked_array("targets", targets, (k, self.nu))

    def checked_targets(self, targets) -> np.ndarray:
        targets = np.asarray(targets, dtype=float)
        if targets.shape != (self.nworld, self.nu):
            raise ConfigError(f"targets must have shape {(self.nworld, self.nu)}, got {targets.shape}")
        return targets


def checked_array(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    """`value` as a float array of `shape`; ConfigError if the shape differs or a value is not finite."""
    value = np.asarray(value, dtype=float)
    if value.shape != shape:
        raise ConfigError(f"{name} must have shape {shape}, got {value.shape}")
    if not np.all(np.isfinite(value)):
        raise ConfigError(f"{name} contains non-finite values")
    return value
