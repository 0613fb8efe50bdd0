"""Manipulation as a skill: hands along waypoint paths, grasps as point contacts, a held object as a
payload, and the record's hand forces while it is held.

- `HandPath`: each hand's target position over a phase, a smoothstep between two waypoints.
- `grasp_contacts`: the hands as 3D point contacts at grasp points, each friction cone's normal the
  outward normal of the face it presses on (the force on the robot pushes the hand out of the face).
- Carrying: a phase with `payload` has the object's mass split between the hands (its centre of
  mass exact, its rotational inertia left out) and a `squeeze` the arms hold inside the solver's
  dynamics (`trajopt.squeeze`; `hold_squeeze` sizes it for friction to carry the object).
  `held_object_forces` writes the record's hand forces of those phases: each hand gets the object's
  share of its dynamics, m_i (g - a_i), plus the equal and opposite squeeze along the line between
  the hands. The squeeze pair exerts no net force or moment on the robot (its forces are opposite
  and on one line), so the robot-only equations of motion of every frame balance exactly with the
  solver's torques.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import pinocchio as pin

from opt2skill.data.record import FRAME_DT
from opt2skill.model.robot import Robot
from opt2skill.trajopt.frames import Frames
from opt2skill.trajopt.phases import Contact, Problem
from opt2skill.trajopt.skills.gait import smoothstep

GRAVITY = np.array([0.0, 0.0, -9.81])


@dataclass(frozen=True)
class HandPath:
    """Targets of the hands (name -> position) moving from `start` to `end` over [t0, t0 + duration]."""

    start: dict[str, np.ndarray]
    end: dict[str, np.ndarray]
    t0: float
    duration: float

    def at(self, t: float) -> dict[str, np.ndarray]:
        s = smoothstep((t - self.t0) / self.duration)
        return {h: self.start[h] + (self.end[h] - self.start[h]) * s for h in self.start}

    def motion(self, hand: str, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration of `hand`'s target at t (zero speed at both ends)."""
        u = float(np.clip((t - self.t0) / self.duration, 0.0, 1.0))
        d = self.end[hand] - self.start[hand]
        rate = 1.0 / self.duration
        return (self.start[hand] + d * smoothstep(u), d * (6 * u - 6 * u * u) * rate,
                d * (6 - 12 * u) * rate**2 if 0.0 < u < 1.0 else 0.0 * d)


def normal_frame(normal: np.ndarray) -> np.ndarray:
    """A rotation whose z axis is `normal` (the friction cone's axis)."""
    z = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def grasp_contacts(points: dict[str, np.ndarray], normals: dict[str, np.ndarray]) -> tuple[Contact, ...]:
    return tuple(Contact(h, pin.SE3(normal_frame(normals[h]), np.asarray(points[h], dtype=float)), flat=False)
                 for h in points)


def end_effector_positions(robot: Robot, q: np.ndarray, names) -> dict[str, np.ndarray]:
    """World positions of end effectors (robot config names) at configuration q (Pinocchio's)."""
    data = robot.pin_model.createData()
    pin.framesForwardKinematics(robot.pin_model, data, q)
    return {n: data.oMf[robot.pin_frame_id(robot.config.end_effectors[n])].translation.copy() for n in names}


def contact_radius(robot: Robot, name: str) -> float:
    """How far end effector `name`'s site lies inside the surface it rests on: the largest radius of
    the collision spheres and capsules around it (a hand's sphere; at an elbow, the capsules of the
    upper arm and forearm that end there); 0 without one."""
    model = robot.mj_model
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    point = data.site_xpos[robot.site_id(robot.config.end_effectors[name])]
    radii = [0.0]
    for g in range(model.ngeom):
        kind = int(model.geom_type[g])
        if kind == int(mujoco.mjtGeom.mjGEOM_SPHERE):
            a = b = data.geom_xpos[g]
        elif kind == int(mujoco.mjtGeom.mjGEOM_CAPSULE):
            half = model.geom_size[g, 1] * data.geom_xmat[g].reshape(3, 3)[:, 2]
            a, b = data.geom_xpos[g] - half, data.geom_xpos[g] + half
        else:
            continue
        s = np.clip(np.dot(point - a, b - a) / max(float(np.dot(b - a, b - a)), 1e-12), 0.0, 1.0)
        if np.linalg.norm(a + s * (b - a) - point) < 1e-3:
            radii.append(float(model.geom_size[g, 0]))
    return max(radii)


def sliding_contact(hand: str, path: HandPath, normal: np.ndarray, min_normal_force: float | None = None) -> Contact:
    """`hand` as a point contact sliding along `path` on a surface with outward `normal` (wiping,
    drawing): its friction cone opens along the normal, its Baumgarte reference follows the path."""
    start = np.asarray(path.start[hand], dtype=float)
    return Contact(hand, pin.SE3(normal_frame(normal), start), flat=False,
                   path=lambda t: path.motion(hand, t), min_normal_force=min_normal_force)


def hold_squeeze(mass: float, mu: float, margin: float, acceleration: float) -> float:
    """N each of two hands must press on an object of `mass` kg held between them so that friction
    (coefficient `mu`) carries its half of the weight while it accelerates by up to `acceleration`
    m/s^2 in any direction, with `margin` (> 1) on that."""
    return margin * (mass / 2.0) * (abs(GRAVITY[2]) + acceleration) / mu


def held_object_forces(robot: Robot, problem: Problem, frames: Frames, knots: dict, hands: tuple[str, str]) -> None:
    """Fill the hands' forces of `frames` and the solver's `knots` (in place) over the phases that
    carry a payload: each hand's share of the object's dynamics, m_i (g - a_i), plus the phase's
    squeeze pushing it away from the other hand along the line between them. The squeeze's torques
    are already the solver's (`Phase.squeeze`, `trajopt.squeeze`). At an impulse node while
    carrying (a foot touching down during a walk) the knot's hand impulses are the object's share
    of the impact, -m_i (dv_i), the change of the hand's velocity (N s)."""
    hold = _Hold(robot, problem, hands)
    nq = robot.pin_model.nq
    x = np.asarray(knots["x"])
    v_next = np.vstack([frames.v[1:], frames.v[-1:]])
    for k, node in enumerate(problem.nodes[:-1]):
        phase = problem.phases[node.phase_index]
        if not phase.payload:
            continue
        masses = np.array([dict(phase.payload)[h] for h in hands])
        if node.kind == "impulse":  # a foot's touchdown while carrying: the object's impulse on the hands
            hold.impulse(x[k, :nq], x[k + 1, nq:] - x[k, nq:], masses, knots["contact_force"][k])
            continue
        rows = np.arange(int(round(node.time / FRAME_DT)), int(round((node.time + node.dt) / FRAME_DT)))
        a = (v_next[rows] - frames.v[rows]) / FRAME_DT
        hold.apply(frames.q[rows], frames.v[rows], a, masses, phase.squeeze, rows, frames.wrench, frames.active)
        v = x[k, nq:]
        hold.apply(x[k : k + 1, :nq], v[None], ((x[k + 1, nq:] - v) / node.dt)[None], masses, phase.squeeze,
                   np.array([k]), knots["contact_force"], np.zeros(knots["contact_force"].shape[:2], dtype=bool))


class _Hold:
    """The hands' share of a held object's dynamics plus the squeeze, as contact forces."""

    def __init__(self, robot: Robot, problem: Problem, hands: tuple[str, str]):
        self.pm = robot.pin_model
        self.pd = self.pm.createData()
        self.fids = [robot.pin_frame_id(robot.config.end_effectors[h]) for h in hands]
        self.cols = [list(problem.contact_names).index(h) for h in hands]

    def impulse(self, q, dv, masses, out) -> None:
        """The hands' impulses -m_i J_i(q) dv (N s) into out[hand columns] (the node's (nc, 6))."""
        pm, pd = self.pm, self.pd
        pin.computeJointJacobians(pm, pd, q)
        pin.updateFramePlacements(pm, pd)
        for i, (fid, c) in enumerate(zip(self.fids, self.cols)):
            J = pin.getFrameJacobian(pm, pd, fid, pin.LOCAL_WORLD_ALIGNED)[:3]
            out[c, :3] = -masses[i] * (J @ dv)
            out[c, 3:] = 0.0

    def apply(self, q, v, a, masses, squeeze, rows, wrench, active) -> None:
        """Per state r: the first hand's force m_1 (g - a_1) + s axis, the second's m_2 (g - a_2) - s
        axis (axis: the unit vector from the second hand to the first), into wrench[rows[r]]."""
        pm, pd = self.pm, self.pd
        for r, k in enumerate(rows):
            pin.forwardKinematics(pm, pd, q[r], v[r], a[r])
            pin.updateFramePlacements(pm, pd)
            gap = pd.oMf[self.fids[0]].translation - pd.oMf[self.fids[1]].translation
            push = squeeze * gap / np.linalg.norm(gap)
            for i, (fid, c) in enumerate(zip(self.fids, self.cols)):
                accel = pin.getFrameClassicalAcceleration(pm, pd, fid, pin.LOCAL_WORLD_ALIGNED).linear
                wrench[k, c, :3] = masses[i] * (GRAVITY - accel) + (push if i == 0 else -push)
                wrench[k, c, 3:] = 0.0
                active[k, c] = True


def held_object_poses(robot: Robot, q: np.ndarray, held: np.ndarray, hands: tuple[str, str],
                      rest: np.ndarray, put: np.ndarray | None = None) -> np.ndarray:
    """(T, 7) reference pose (x y z, quaternion w x y z) of an object two hands pick up and put down.

    It rests at `rest` (7,) until the first frame of `held` (T,) bool, follows the hands rigidly from
    there to the last held frame (its pose in the hands' frame fixed at the grasp instant), and rests
    at `put` (7,) afterwards (where it was at the release when `put` is None). The hands' frame: origin between the hand sites, y from the second
    hand to the first, z as close to world up as that allows. `q` (T, nq): Pinocchio configurations.
    """
    rest = np.asarray(rest, dtype=float)
    out = np.tile(rest, (len(q), 1))
    rows = np.flatnonzero(held)
    if not len(rows):
        return out
    first, last = int(rows[0]), int(rows[-1])
    pm, pd = robot.pin_model, robot.pin_model.createData()
    fids = [robot.pin_frame_id(robot.config.end_effectors[h]) for h in hands]
    origin, rot = np.zeros((last - first + 1, 3)), np.zeros((last - first + 1, 3, 3))
    for r, k in enumerate(range(first, last + 1)):
        pin.framesForwardKinematics(pm, pd, q[k])
        a, b = (pd.oMf[f].translation for f in fids)
        y = (a - b) / np.linalg.norm(a - b)
        x = np.cross(y, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        origin[r], rot[r] = (a + b) / 2, np.column_stack([x, y, np.cross(x, y)])
    rest_rot = pin.Quaternion(*rest[3:]).toRotationMatrix()  # Pinocchio's constructor takes w, x, y, z
    local_pos = rot[0].T @ (rest[:3] - origin[0])
    local_rot = rot[0].T @ rest_rot
    for r, k in enumerate(range(first, last + 1)):
        quat = pin.Quaternion(rot[r] @ local_rot).coeffs()  # x, y, z, w
        out[k] = np.r_[origin[r] + rot[r] @ local_pos, quat[3], quat[:3]]
    out[last + 1:] = out[last] if put is None else put
    return out
