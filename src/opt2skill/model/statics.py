"""Static balance in Pinocchio: joint torques and foot wrenches that hold a pose against gravity."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from opt2skill.model.convert import qpos_mj_to_pin
from opt2skill.model.robot import Robot

# Weight of the wrench norm against the torque norm: small, so torques are minimised and the
# split between the feet is still unique.
_WRENCH_WEIGHT = 1e-4


@dataclass(frozen=True)
class StaticBalance:
    torque: np.ndarray  # (nu,) joint torques, N m
    wrenches: np.ndarray  # (nfeet, 6) force and torque at each sole site, world-aligned axes
    residual: float  # largest |M qdd + h - B u - J^T F| with qdd = 0 (N or N m)


def gravity_compensation(robot: Robot, qpos: np.ndarray) -> StaticBalance:
    """Torques u and sole wrenches F with g(q) = B u + J_c^T F, minimising |u|^2 (+ a little |F|^2).

    The six base rows are equality constraints (the feet carry the weight); the solution is the
    minimiser of the KKT system. `qpos` is in MuJoCo's layout.
    """
    pm = robot.pin_model
    pd = pm.createData()
    q = qpos_mj_to_pin(qpos)
    g = pin.computeGeneralizedGravity(pm, pd, q)
    pin.computeJointJacobians(pm, pd, q)
    pin.updateFramePlacements(pm, pd)
    J = np.vstack(
        [pin.getFrameJacobian(pm, pd, robot.pin_frame_id(f.sole_site), pin.LOCAL_WORLD_ALIGNED) for f in robot.config.feet]
    )
    A, B = J[:, 6:].T, J[:, :6].T  # joint rows and base rows of J^T
    g_j, g_b = g[6:], g[:6]
    n = J.shape[0]
    H = A.T @ A + _WRENCH_WEIGHT * np.eye(n)
    kkt = np.block([[H, B.T], [B, np.zeros((6, 6))]])
    rhs = np.concatenate([A.T @ g_j, g_b])
    F = np.linalg.lstsq(kkt, rhs, rcond=None)[0][:n]
    u = g_j - A @ F
    residual = np.abs(g - np.concatenate([np.zeros(6), u]) - J.T @ F).max()
    return StaticBalance(torque=u, wrenches=F.reshape(len(robot.config.feet), 6), residual=float(residual))
