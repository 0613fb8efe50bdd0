"""Stabilizing feedback gains for the standing segments of a reference, from an infinite-horizon LQR.

DDP's gains come from a finite horizon: near its end they follow the terminal cost, not the
dynamics, and held past the end they let the robot fall (measured: 2 of 3 walks fell within 3 s of
standing on the last node's gain, none with the gain here; docs/expert.md). A standing segment (all
feet in contact for at least `min_duration`) gets a gain of its own instead: the discrete-time LQR of
the optimizer's contact dynamics (Crocoddyl's `DifferentialActionModelContactFwdDynamics`, the feet
as 6D contacts held where they stand, semi-implicit Euler at the 5-ms frame step) linearized at the
segment's middle frame, `scipy.linalg.solve_discrete_are` for the Riccati equation. The gain acts
on the same tangent-space deviation as DDP's (u = u_ref - K (x (-) x_ref)).

A gain is a function of the robot, the frame's state, torque and contacts, and the weights only, so
each is solved once per process (`GAIN_CACHE`): a distillation builds the expert for its own stage
and again for the PPO stage's anchor, and about 10 ms of Riccati solve per segment adds up to
seconds on a hundred references.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Collection
from dataclasses import dataclass

import crocoddyl
import numpy as np
import pinocchio as pin
from scipy.linalg import solve_discrete_are

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.errors import DataError
from opt2skill.model.convert import qpos_mj_to_pin, qvel_mj_to_pin
from opt2skill.model.robot import Robot


@dataclass(frozen=True)
class StandingLQR:
    """Weights of the standing LQR (per unit time; state costs on the tangent-space deviation)."""

    min_duration: float = 0.4  # s of all feet in contact that make a standing segment
    # In records with other contacts (hands on a box) the feet-only stretches also carry the arms'
    # reach and return, which one gain does not hold (docs/expert.md): there only the frames where
    # every joint is slower than this (rad/s) count.
    rest_speed: float = 0.5
    base_pose: float = 1e3  # base translation and rotation
    joint_position: float = 1e2
    base_velocity: float = 10.0
    joint_velocity: float = 1.0
    torque: float = 1.0  # on (u / torque limit)^2
    baumgarte: tuple[float, float] = (100.0, 20.0)  # contact stabilization, as the optimizer's


def standing_segments(traj: Trajectory, weights: StandingLQR, feet: Collection[str]) -> list[tuple[int, int]]:
    """Frame ranges [start, stop), at least `weights.min_duration` long, where every foot is in
    contact and nothing else is; in a record with other contacts, also with the joints at rest
    (`weights.rest_speed`)."""
    names = list(traj.contact_names)
    is_foot = np.array([name in feet for name in names], dtype=bool)
    if not is_foot.any():
        return []
    active = np.asarray(traj.contact_active, dtype=bool)
    standing = active[:, is_foot].all(axis=1) & ~active[:, ~is_foot].any(axis=1)
    if not is_foot.all():
        standing &= np.abs(traj.qvel[:, 6:]).max(axis=1) <= weights.rest_speed
    on = np.r_[0, standing.astype(np.int8), 0]
    edges = np.diff(on)
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    shortest = int(round(weights.min_duration / FRAME_DT))
    return [(int(a), int(b)) for a, b in zip(starts, stops) if b - a >= shortest]


class GainCache:
    """The newest `size` gains solved in this process, by what decides them."""

    def __init__(self, size: int = 4096):  # 4 kB each for Digit: at most 16 MB
        self.size, self._gains = size, OrderedDict()
        self.solved = 0  # Riccati equations solved (the misses)

    @staticmethod
    def key(robot: Robot, traj: Trajectory, frame: int, weights: StandingLQR) -> tuple:
        state = hashlib.sha1()
        for part in (traj.qpos[frame], traj.qvel[frame], traj.joint_torque[frame], traj.contact_active[frame]):
            state.update(np.ascontiguousarray(part).tobytes())
        return robot.hash, tuple(traj.contact_names), state.hexdigest(), weights

    def get(self, key: tuple) -> np.ndarray | None:
        gain = self._gains.get(key)
        if gain is not None:
            self._gains.move_to_end(key)
        return gain

    def put(self, key: tuple, gain: np.ndarray) -> None:
        gain.setflags(write=False)  # shared by every expert that asks: nobody may change it
        self._gains[key] = gain
        self.solved += 1
        while len(self._gains) > self.size:
            self._gains.popitem(last=False)


GAIN_CACHE = GainCache()


def standing_gain(robot: Robot, traj: Trajectory, frame: int, weights: StandingLQR) -> np.ndarray:
    """The LQR gain (nu, 2 nv) at one frame of a standing segment (float32, like the stored gains;
    read-only: solved once per process, `GAIN_CACHE`)."""
    key = GainCache.key(robot, traj, frame, weights)
    gain = GAIN_CACHE.get(key)
    if gain is None:
        gain = _solve_standing_gain(robot, traj, frame, weights)
        GAIN_CACHE.put(key, gain)
    return gain


def _solve_standing_gain(robot: Robot, traj: Trajectory, frame: int, weights: StandingLQR) -> np.ndarray:
    feet = {foot.name: foot for foot in robot.config.feet}
    in_contact = [name for name, on in zip(traj.contact_names, traj.contact_active[frame]) if on]
    unknown = [name for name in in_contact if name not in feet]
    if unknown:
        raise DataError(f"standing gains need flat foot contacts only; frame {frame} also has {unknown}")
    pm = robot.pin_model
    q = qpos_mj_to_pin(traj.qpos[frame])
    x = np.concatenate([q, qvel_mj_to_pin(traj.qpos[frame], traj.qvel[frame])])
    state = crocoddyl.StateMultibody(pm)
    actuation = crocoddyl.ActuationModelFloatingBase(state)
    data = pm.createData()
    pin.framesForwardKinematics(pm, data, q)
    contacts = crocoddyl.ContactModelMultiple(state, actuation.nu)
    for name in in_contact:
        fid = robot.pin_frame_id(feet[name].sole_site)
        contacts.addContact(name, crocoddyl.ContactModel6D(state, fid, data.oMf[fid], pin.LOCAL, actuation.nu,
                                                           np.array(weights.baumgarte)))
    dynamics = crocoddyl.DifferentialActionModelContactFwdDynamics(
        state, actuation, contacts, crocoddyl.CostModelSum(state, actuation.nu))
    step = crocoddyl.IntegratedActionModelEuler(dynamics, FRAME_DT)
    step_data = step.createData()
    u = traj.joint_torque[frame]
    step.calc(step_data, x, u)
    step.calcDiff(step_data, x, u)
    A, B = np.array(step_data.Fx), np.array(step_data.Fu)
    nu = robot.nu
    Q = FRAME_DT * np.diag(np.r_[np.full(6, weights.base_pose), np.full(nu, weights.joint_position),
                                 np.full(6, weights.base_velocity), np.full(nu, weights.joint_velocity)])
    R = FRAME_DT * weights.torque * np.diag(1.0 / robot.config.torque_limit ** 2)
    P = solve_discrete_are(A, B, Q, R)
    return np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A).astype(np.float32)
