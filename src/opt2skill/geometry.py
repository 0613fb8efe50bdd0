"""Batched rotation helpers. Quaternions are (w, x, y, z), MuJoCo's order; leading dims broadcast."""

from __future__ import annotations

import numpy as np


def quat_to_mat(quat: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from unit quaternions (..., 4)."""
    w, x, y, z = np.moveaxis(np.asarray(quat, dtype=float), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, dtype=float), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, dtype=float), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def quat_conj(q: np.ndarray) -> np.ndarray:
    return np.asarray(q, dtype=float) * np.array([1.0, -1.0, -1.0, -1.0])


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., 3) from body to world by q."""
    return np.einsum("...ij,...j->...i", quat_to_mat(q), v)


def rotate_inv(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., 3) from world to body by q."""
    return np.einsum("...ji,...j->...i", quat_to_mat(q), v)


def quat_error(q_ref: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rotation vector (..., 3) of q_ref^-1 * q: the orientation error, in the reference frame.

    Its norm is the geodesic angle between the two orientations, whatever the quaternions' signs.
    """
    dq = quat_mul(quat_conj(q_ref), q)
    dq = np.where(dq[..., :1] < 0, -dq, dq)
    vec = dq[..., 1:]
    sin_half = np.linalg.norm(vec, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, dq[..., :1])
    scale = np.where(sin_half > 1e-12, angle / np.maximum(sin_half, 1e-300), 2.0)
    return vec * scale


def tilt_angle(q: np.ndarray) -> np.ndarray:
    """Angle (rad) between the body z axis and the world z axis."""
    z_world = quat_to_mat(q)[..., 2, 2]
    return np.arccos(np.clip(z_world, -1.0, 1.0))


def yaw_of(q: np.ndarray) -> np.ndarray:
    """Heading angle (rad) of the body x axis projected on the ground plane."""
    m = quat_to_mat(q)
    return np.arctan2(m[..., 1, 0], m[..., 0, 0])


def projected_gravity(q: np.ndarray) -> np.ndarray:
    """Unit gravity direction expressed in the body frame (the usual IMU tilt observation)."""
    return rotate_inv(q, np.broadcast_to(np.array([0.0, 0.0, -1.0]), np.shape(q)[:-1] + (3,)))
