"""State conversions between MuJoCo and Pinocchio. Nothing else in the package converts by hand.

MuJoCo: qpos = [p, quat (w, x, y, z), joints]; qvel = [linear velocity in the WORLD frame,
angular velocity in the BODY frame, joint velocities].
Pinocchio: q = [p, quat (x, y, z, w), joints]; v = [linear velocity in the BODY frame, angular
velocity in the BODY frame, joint velocities].
So v_mj = T v_pin with T = blockdiag(R, I), R the base rotation. All functions take arrays with any
leading (batch) dimensions.
"""

from __future__ import annotations

import numpy as np

from opt2skill.geometry import quat_to_mat, rotate, rotate_inv


def qpos_mj_to_pin(qpos: np.ndarray) -> np.ndarray:
    q = np.array(qpos, dtype=float, copy=True)
    q[..., 3:7] = np.asarray(qpos)[..., [4, 5, 6, 3]]
    return q


def qpos_pin_to_mj(q: np.ndarray) -> np.ndarray:
    qpos = np.array(q, dtype=float, copy=True)
    qpos[..., 3:7] = np.asarray(q)[..., [6, 3, 4, 5]]
    return qpos


def qvel_mj_to_pin(qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    v = np.array(qvel, dtype=float, copy=True)
    v[..., :3] = rotate_inv(np.asarray(qpos)[..., 3:7], np.asarray(qvel)[..., :3])
    return v


def qvel_pin_to_mj(qpos: np.ndarray, v: np.ndarray) -> np.ndarray:
    """`qpos` is MuJoCo's layout (the base orientation is all that is used)."""
    qvel = np.array(v, dtype=float, copy=True)
    qvel[..., :3] = rotate(np.asarray(qpos)[..., 3:7], np.asarray(v)[..., :3])
    return qvel


def qacc_pin_to_mj(qpos: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Pinocchio's base acceleration is spatial; MuJoCo's is the classical one of the base origin."""
    a = np.asarray(a, dtype=float)
    v = np.asarray(v, dtype=float)
    qacc = a.copy()
    classical = a[..., :3] + np.cross(v[..., 3:6], v[..., :3])
    qacc[..., :3] = rotate(np.asarray(qpos)[..., 3:7], classical)
    return qacc


def qacc_mj_to_pin(qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray) -> np.ndarray:
    v = qvel_mj_to_pin(qpos, qvel)
    a = np.array(qacc, dtype=float, copy=True)
    a[..., :3] = rotate_inv(np.asarray(qpos)[..., 3:7], np.asarray(qacc)[..., :3]) - np.cross(v[..., 3:6], v[..., :3])
    return a


def gen_force_mj_to_pin(qpos: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Generalized forces transform with T^T (equal power): base force from world to body axes."""
    out = np.array(f, dtype=float, copy=True)
    out[..., :3] = rotate_inv(np.asarray(qpos)[..., 3:7], np.asarray(f)[..., :3])
    return out


def gen_force_pin_to_mj(qpos: np.ndarray, f: np.ndarray) -> np.ndarray:
    out = np.array(f, dtype=float, copy=True)
    out[..., :3] = rotate(np.asarray(qpos)[..., 3:7], np.asarray(f)[..., :3])
    return out


def velocity_map(qpos: np.ndarray, nv: int) -> np.ndarray:
    """T (nv x nv) with v_mj = T v_pin, for one configuration."""

    T = np.eye(nv)
    T[:3, :3] = quat_to_mat(np.asarray(qpos)[3:7])
    return T
