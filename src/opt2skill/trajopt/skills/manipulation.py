"""Manipulation as a skill: hands along waypoint paths, grasps as point contacts, a held object as a
payload, and the record's hand forces while it is held.

- `HandPath`: each hand's target position over a phase, a smoothstep between two waypoints.
- `grasp_contacts`: the hands as 3D point contacts at grasp points, each friction cone's normal the
  outward normal of the face it presses on (the force on the robot pushes the hand out of the face).
- Carrying: a phase with `payload` has the object's mass split between the hands (its centre of
  mass exact, its rotational inertia left out). `held_object_forces` turns the optimizer's frames of
  those phases into the record's: each hand gets the object's share of its dynamics, m_i (g - a_i),
  plus an equal and opposite squeeze along the line between the hands, large enough for friction
  to hold the object; the squeeze's joint torques are added to the arms. The squeeze pair exerts no
  net force or moment on the robot (its forces are opposite and on one line), so the robot-only
  equations of motion of every frame still balance exactly.
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


def held_object_forces(robot: Robot, problem: Problem, frames: Frames, knots: dict, hands: tuple[str, str],
                       mass: float, mu: float, margin: float = 1.5, min_squeeze: float = 10.0) -> float:
    """Fill `frames` and the solver's `knots` (in place) over the phases that carry a payload: the
    hands' forces and the squeeze's torques; returns the squeeze (N). `mu`: the hand-object friction
    the squeeze must respect, with `margin` on the largest tangential force."""
    hold = _Hold(robot, problem, hands, mass / 2.0)
    rows = np.flatnonzero(_carried_frames(problem, len(frames.q)))
    if not len(rows):
        return 0.0
    nq = robot.pin_model.nq
    v_next = np.vstack([frames.v[1:], frames.v[-1:]])
    shares, axes = hold.shares(frames.q[rows], frames.v[rows], (v_next[rows] - frames.v[rows]) / FRAME_DT)
    # Squeeze: the first hand is pushed along +axis (out of the object), the second along -axis.
    along = np.stack([np.einsum("ij,ij->i", shares[:, 0], axes), -np.einsum("ij,ij->i", shares[:, 1], axes)], 1)
    tangential = np.linalg.norm(shares - along[:, :, None] * np.stack([axes, -axes], 1), axis=2)
    squeeze = max(min_squeeze, float(np.max(margin * tangential / mu - along)))
    hold.apply(frames.q[rows], shares, axes, squeeze, frames.tau, frames.wrench, frames.active, rows)
    running = [k for k, node in enumerate(problem.nodes[:-1])
               if node.kind == "running" and problem.phases[node.phase_index].payload]
    if running:
        x = np.asarray(knots["x"])
        dt = np.asarray(knots["dt"])[running]
        q, v = x[running, :nq], x[running, nq:]
        shares, axes = hold.shares(q, v, (x[np.array(running) + 1, nq:] - v) / dt[:, None])
        active = np.zeros(knots["contact_force"].shape[:2], dtype=bool)
        hold.apply(q, shares, axes, squeeze, knots["u"], knots["contact_force"], active, np.array(running))
    return squeeze


class _Hold:
    """The hands' share of a held object's dynamics, and the squeeze's forces and torques."""

    def __init__(self, robot: Robot, problem: Problem, hands: tuple[str, str], share: float):
        self.pm = robot.pin_model
        self.pd = self.pm.createData()
        self.fids = [robot.pin_frame_id(robot.config.end_effectors[h]) for h in hands]
        self.cols = [list(problem.contact_names).index(h) for h in hands]
        self.share = share

    def shares(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """m_i (g - a_i) at each hand (n, 2, 3) and the unit axis from the second hand to the first."""
        pm, pd = self.pm, self.pd
        forces, axes = np.zeros((len(q), 2, 3)), np.zeros((len(q), 3))
        for r in range(len(q)):
            pin.forwardKinematics(pm, pd, q[r], v[r], a[r])
            pin.updateFramePlacements(pm, pd)
            for i, fid in enumerate(self.fids):
                forces[r, i] = self.share * (GRAVITY - pin.getFrameClassicalAcceleration(pm, pd, fid, pin.LOCAL_WORLD_ALIGNED).linear)
            d = pd.oMf[self.fids[0]].translation - pd.oMf[self.fids[1]].translation
            axes[r] = d / np.linalg.norm(d)
        return forces, axes

    def apply(self, q, shares, axes, squeeze, tau, wrench, active, rows) -> None:
        pm, pd = self.pm, self.pd
        for r, k in enumerate(rows):
            pin.computeJointJacobians(pm, pd, q[r])
            pin.updateFramePlacements(pm, pd)
            push = (squeeze * axes[r], -squeeze * axes[r])
            generalized = sum(pin.getFrameJacobian(pm, pd, fid, pin.LOCAL_WORLD_ALIGNED)[:3].T @ p
                              for fid, p in zip(self.fids, push))
            tau[k] -= generalized[6:]  # the arms hold the squeeze; its base part is zero
            for i, c in enumerate(self.cols):
                wrench[k, c, :3] = shares[r, i] + push[i]
                wrench[k, c, 3:] = 0.0
                active[k, c] = True


def _carried_frames(problem: Problem, n_frames: int) -> np.ndarray:
    """(T,) bool: frames whose step lies in a phase with a payload (by the nodes' times)."""
    out = np.zeros(n_frames, dtype=bool)
    for node in problem.nodes:
        if node.kind == "running" and problem.phases[node.phase_index].payload:
            k0 = int(round(node.time / FRAME_DT))
            out[k0 : k0 + int(round(node.dt / FRAME_DT))] = True
    return out


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
