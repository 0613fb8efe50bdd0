"""Batched state differences in Crocoddyl's convention (Pinocchio layout), for many worlds at once.

`state_diff(x0, x1)` equals crocoddyl.StateMultibody.diff for a free-flyer robot with revolute
joints: the free flyer's difference is the SE(3) logarithm of M0^-1 M1 (linear part first, in the
frame of M0), joints and velocities subtract. Tested against Pinocchio to machine precision.
"""

from __future__ import annotations

import numpy as np


def _quat_xyzw_to_mat(q: np.ndarray) -> np.ndarray:
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _skew(w: np.ndarray) -> np.ndarray:
    z = np.zeros(w.shape[:-1])
    return np.stack(
        [np.stack([z, -w[..., 2], w[..., 1]], -1), np.stack([w[..., 2], z, -w[..., 0]], -1),
         np.stack([-w[..., 1], w[..., 0], z], -1)],
        -2,
    )


def se3_log(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """log of (R, p) as a twist [v, w] (..., 6)."""
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    theta = np.arccos(cos)
    sin = np.sin(theta)
    small = theta < 1e-4
    safe_theta = np.where(small, 1.0, theta)
    # w = theta / sin(theta) * vee(R - R^T) / 2 (series near zero).
    vee = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1) / 2
    w = vee * np.where(small, 1 + theta**2 / 6, safe_theta / np.where(small, 1.0, sin))[..., None]
    # v = V^-1 p, V^-1 = I - W/2 + c W^2 with c = (1 - theta sin / (2 (1 - cos))) / theta^2 (series near zero).
    c = np.where(
        small,
        1 / 12 + theta**2 / 720,
        (1 - safe_theta * sin / np.where(small, 1.0, 2 * (1 - cos))) / safe_theta**2,
    )
    W = _skew(w)
    Wp = np.einsum("...ij,...j->...i", W, p)
    v = p - 0.5 * Wp + c[..., None] * np.einsum("...ij,...j->...i", W, Wp)
    return np.concatenate([v, w], -1)


def state_diff(x0: np.ndarray, x1: np.ndarray, nq: int) -> np.ndarray:
    """x1 (-) x0 in the tangent space (..., 2 nv), states in Pinocchio layout (..., nq + nv)."""
    q0, q1 = x0[..., :nq], x1[..., :nq]
    R0, R1 = _quat_xyzw_to_mat(q0[..., 3:7]), _quat_xyzw_to_mat(q1[..., 3:7])
    R0t = np.swapaxes(R0, -1, -2)
    base = se3_log(R0t @ R1, np.einsum("...ij,...j->...i", R0t, q1[..., :3] - q0[..., :3]))
    return np.concatenate([base, q1[..., 7:] - q0[..., 7:], x1[..., nq:] - x0[..., nq:]], -1)
