"""Physical checks of a trajectory record: dynamics, contacts, limits, slip, derived fields.

Each function measures one thing on a `Trajectory` and returns figures (floats, SI units unless
the name says otherwise). Thresholds and the accept/reject decision live in `validate.py`.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pinocchio as pin

from opt2skill.data.record import FRAME_DT, Trajectory, build_trajectory
from opt2skill.model.convert import qpos_mj_to_pin, qvel_mj_to_pin
from opt2skill.model.robot import Robot

def _contact_frames(robot: Robot, contact_names: tuple[str, ...]) -> list[int]:
    return [robot.pin_frame_id(robot.config.end_effectors[name]) for name in contact_names]


def dynamics_residual(
    robot: Robot,
    q: np.ndarray,
    v: np.ndarray,
    v_next: np.ndarray,
    dt: np.ndarray,
    torque: np.ndarray,
    wrench: np.ndarray,
    contact_names: tuple[str, ...],
) -> np.ndarray:
    """Residual of the equations of motion at each step, Pinocchio coordinates, (n, nv), N and N m.

    dt > 0: M(q) a + h(q, v) - B u - sum_c J_c^T F_c with a = (v_next - v) / dt, the acceleration
    that semi-implicit Euler (Crocoddyl's integrator) applies over the step.
    dt == 0 (an impact): M(q) (v_next - v) - sum_c J_c^T Lambda_c, with `wrench` holding impulses
    (N s) and the torque not entering.
    Wrenches are on the robot at each contact site, world-aligned axes (the record's convention).
    """
    pm = robot.pin_model
    pd = pm.createData()
    frames = _contact_frames(robot, contact_names)
    n = len(q)
    out = np.empty((n, pm.nv))
    for k in range(n):
        pin.computeJointJacobians(pm, pd, q[k])
        pin.updateFramePlacements(pm, pd)
        contact = np.zeros(pm.nv)
        for c, fid in enumerate(frames):
            J = pin.getFrameJacobian(pm, pd, fid, pin.LOCAL_WORLD_ALIGNED)
            contact += J.T @ wrench[k, c]
        dv = v_next[k] - v[k]
        if dt[k] > 0:
            tau = pin.rnea(pm, pd, q[k], v[k], dv / dt[k])
            tau[6:] -= torque[k]
        else:
            tau = pin.crba(pm, pd, q[k])
            tau = np.triu(tau) + np.triu(tau, 1).T  # crba fills the upper triangle
            tau = tau @ dv
        out[k] = tau - contact
    return out


def frame_dynamics_residual(robot: Robot, traj: Trajectory) -> np.ndarray:
    """`dynamics_residual` between consecutive 200 Hz frames, (T-1, nv)."""
    q = qpos_mj_to_pin(traj.qpos)
    v = qvel_mj_to_pin(traj.qpos, traj.qvel)
    dt = np.full(len(q) - 1, FRAME_DT)
    return dynamics_residual(
        robot, q[:-1], v[:-1], v[1:], dt, traj.joint_torque[:-1], traj.contact_wrench[:-1], traj.contact_names
    )


def touchdown_frames(active: np.ndarray) -> np.ndarray:
    """(T-1,) bool: steps k -> k+1 during which some contact becomes active (an impact happens)."""
    return np.any(active[1:] & ~active[:-1], axis=1)


def site_poses(robot: Robot, qpos: np.ndarray, sites: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """World positions (T, n, 3) and rotations (T, n, 3, 3) of MuJoCo sites along a motion."""
    m = robot.mj_model
    d = mujoco.MjData(m)
    ids = [robot.site_id(s) for s in sites]
    pos = np.empty((len(qpos), len(ids), 3))
    rot = np.empty((len(qpos), len(ids), 3, 3))
    for k in range(len(qpos)):
        d.qpos[:] = qpos[k]
        mujoco.mj_kinematics(m, d)
        pos[k] = d.site_xpos[ids]
        rot[k] = d.site_xmat[ids].reshape(-1, 3, 3)
    return pos, rot


def foot_site_poses(robot: Robot, traj: Trajectory) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Site name -> world positions (T, 3) and rotations (T, 3, 3) of every contact foot's sole and
    corners, in one pass over the motion (the checks below each need some of them)."""
    sites = list(dict.fromkeys(s for _, f in foot_contacts(robot, traj) for s in (f.sole_site, *f.corner_sites)))
    if not sites:
        return {}
    pos, rot = site_poses(robot, traj.qpos, sites)
    return {site: (pos[:, i], rot[:, i]) for i, site in enumerate(sites)}


def _feet_positions(poses: dict, foot) -> np.ndarray:
    """(T, 1 + corners, 3): a foot's sole centre and corners from `foot_site_poses`."""
    return np.stack([poses[s][0] for s in (foot.sole_site, *foot.corner_sites)], axis=1)


def foot_contacts(robot: Robot, traj: Trajectory) -> list[tuple[int, object]]:
    """(position in contact_names, FootConfig) of each contact that is a foot with a flat sole."""
    feet = {f.name: f for f in robot.config.feet}
    return [(c, feet[name]) for c, name in enumerate(traj.contact_names) if name in feet]


def contact_violations(robot: Robot, traj: Trajectory, cop_min_force: float,
                       poses: dict | None = None) -> dict[str, float]:
    """Friction-cone (N), centre-of-pressure (m) and inactive-contact force (N) violations.

    In each active sole's frame: the friction violation is max(0, |f_t| - mu f_n, -f_n); the CoP
    (from the torque about the sole centre) must lie in the sole rectangle, checked where
    f_n > `cop_min_force` (N): a lightly loaded foot's CoP is ill-conditioned and carries almost no
    moment. Contacts other than feet get only the inactive-force check. `poses`: `foot_site_poses`,
    if already computed.
    """
    mu = robot.config.friction_coefficient
    feet = foot_contacts(robot, traj)
    friction = cop = 0.0
    if feet:
        poses = foot_site_poses(robot, traj) if poses is None else poses
        for c, foot in feet:
            active = traj.contact_active[:, c]
            R = poses[foot.sole_site][1][active]
            f = np.einsum("tji,tj->ti", R, traj.contact_wrench[active, c, :3])
            tau = np.einsum("tji,tj->ti", R, traj.contact_wrench[active, c, 3:])
            if not len(f):
                continue
            fn, ft = f[:, 2], np.linalg.norm(f[:, :2], axis=1)
            friction = max(friction, float(np.max(np.maximum(ft - mu * fn, -fn), initial=0.0)))
            loaded = fn > cop_min_force
            cop_x, cop_y = -tau[loaded, 1] / fn[loaded], tau[loaded, 0] / fn[loaded]
            outside = np.maximum(np.abs(cop_x) - foot.half_length, np.abs(cop_y) - foot.half_width)
            cop = max(cop, float(np.max(outside, initial=0.0)))
    inactive = ~traj.contact_active
    inactive_force = float(np.max(np.linalg.norm(traj.contact_wrench[..., :3], axis=-1)[inactive], initial=0.0))
    return {"friction_violation": max(friction, 0.0), "cop_violation": max(cop, 0.0), "inactive_contact_force": inactive_force}


def limit_violations(robot: Robot, traj: Trajectory) -> dict[str, float]:
    """Largest amount beyond the torque (N m), position (rad) and velocity (rad/s) limits."""
    cfg, pm = robot.config, robot.pin_model
    lower, upper = pm.lowerPositionLimit[7:], pm.upperPositionLimit[7:]
    q, qd = traj.qpos[:, 7:], traj.qvel[:, 6:]
    return {
        "torque_violation": float(np.max(np.abs(traj.joint_torque) - cfg.torque_limit, initial=0.0)),
        "joint_limit_violation": float(np.max(np.maximum(lower - q, q - upper), initial=0.0)),
        "velocity_violation": float(np.max(np.abs(qd) - cfg.velocity_limit, initial=0.0)),
    }


def foot_slip(robot: Robot, traj: Trajectory, poses: dict | None = None) -> float:
    """Largest displacement (m) of an active sole's centre or corners since its stance phase began.

    The corners make a sole that turns or tilts in place count as slipping too. `poses`:
    `foot_site_poses`, if already computed.
    """
    feet = foot_contacts(robot, traj)
    if not feet:
        return 0.0
    poses = foot_site_poses(robot, traj) if poses is None else poses
    slip = 0.0
    for c, foot in feet:
        pos = _feet_positions(poses, foot)
        active = traj.contact_active[:, c].astype(np.int8)
        starts = np.flatnonzero(np.diff(np.concatenate([[0], active])) == 1)
        stops = np.flatnonzero(np.diff(np.concatenate([active, [0]])) == -1) + 1
        for a, b in zip(starts, stops):
            slip = max(slip, float(np.linalg.norm(pos[a:b] - pos[a], axis=-1).max()))
    return slip


def foot_penetration(robot: Robot, traj: Trajectory, poses: dict | None = None) -> float:
    """Deepest point (m) of a sole's centre or corners below the ground of the record's scene.
    `poses`: `foot_site_poses`, if already computed."""
    poses = foot_site_poses(robot, traj) if poses is None else poses
    depth = 0.0
    for _, foot in foot_contacts(robot, traj):
        pos = _feet_positions(poses, foot)
        below = traj.scene.ground_height(pos[..., :2]) - pos[..., 2]
        depth = max(depth, float(np.max(below, initial=0.0)))
    return depth


def derived_fields_error(robot: Robot, traj: Trajectory) -> float:
    """Largest difference between the stored derived fields and those recomputed from the state."""
    ref = build_trajectory(
        robot, traj.qpos, traj.qvel, traj.joint_torque, traj.contact_wrench, traj.contact_active,
        task=traj.task, contact_names=traj.contact_names, params=traj.params, seed=traj.seed, ee_names=traj.ee_names,
    )
    fields = ("time", "base_lin_vel", "base_ang_vel", "ee_pos", "ee_pos_base", "com")
    return max(float(np.max(np.abs(getattr(ref, f) - getattr(traj, f)), initial=0.0)) for f in fields)
