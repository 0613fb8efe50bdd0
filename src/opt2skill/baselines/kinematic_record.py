"""A trajectory record from positions alone: velocities by finite differences, no dynamics.

IK and retargeted references have joint angles but no torques or contact forces. Their records
store zeros in `joint_torque` and `contact_wrench` and say so with `has_dynamics=False` and their
`source`; validation then judges only the kinematic figures (docs/data.md).
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from opt2skill.data.record import FRAME_DT, Trajectory, build_trajectory
from opt2skill.model.robot import Robot


def finite_difference_velocity(model: mujoco.MjModel, qpos: np.ndarray, dt: float = FRAME_DT) -> np.ndarray:
    """MuJoCo-layout velocities (T, nv) of positions (T, nq): central differences, one-sided at the ends.

    `mj_differentiatePos` gives the free joint's linear velocity in world axes and its angular
    velocity in the body frame, as `qvel` holds them.
    """
    n = len(qpos)
    qvel = np.zeros((n, model.nv))
    if n < 2:
        return qvel
    for k in range(n):
        a, b = max(k - 1, 0), min(k + 1, n - 1)
        mujoco.mj_differentiatePos(model, qvel[k], (b - a) * dt, qpos[a], qpos[b])
    return qvel


def kinematic_trajectory(
    robot: Robot,
    qpos: np.ndarray,
    contact_active: np.ndarray,
    *,
    task: str,
    source: str,
    contact_names: tuple[str, ...],
    params: dict[str, float],
    seed: int,
    solver: dict[str, Any],
    provenance: dict[str, Any],
) -> Trajectory:
    """The record of a kinematic motion at 200 Hz: zero torques and wrenches, `has_dynamics=False`."""
    qpos = np.asarray(qpos, dtype=float)
    n = len(qpos)
    return build_trajectory(
        robot,
        qpos,
        finite_difference_velocity(robot.mj_model, qpos),
        np.zeros((n, robot.nu)),
        np.zeros((n, len(contact_names), 6)),
        contact_active,
        task=task,
        contact_names=contact_names,
        params=params,
        seed=seed,
        solver=solver,
        provenance=provenance,
        source=source,
        has_dynamics=False,
    )
