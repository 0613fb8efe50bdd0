"""200 Hz frames from a coarse solution: exact steps of the same dynamics under a policy, or interpolation.

`complete` integrates the problem's own contact dynamics at the frame period under a torque policy
per node; `trajopt.tracking.track` (the default completion) and `rollout` are its two policies.
`rollout` integrates the problem's own contact dynamics at the frame period with the
solver's feedback policy u = u_k - K_k (x_ref(t) (-) x), x_ref interpolated between the knots and u
clipped to the torque limits, applying the same impulses at the same instants. Every frame is then
an exact step of Crocoddyl's contact dynamics (semi-implicit Euler at 5 ms): frame k's state,
torque and contact wrenches give frame k+1's velocity, except across a touchdown impulse.

`interpolate` keeps the knots' torques and forces and interpolates the states: cheap, but its
frames are only as consistent as the coarse grid (docs/trajopt.md has the measured residuals).

Both return world-axis wrenches on the robot at each contact point (the contact frame origin).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import crocoddyl
import numpy as np
import pinocchio as pin
from scipy.optimize import nnls

from opt2skill.data.record import FRAME_DT
from opt2skill.errors import SolverError
from opt2skill.trajopt.native import load as load_native
from opt2skill.trajopt.phases import Problem
from opt2skill.trajopt.solver import Solution


@dataclass
class Frames:
    """Frame arrays in Pinocchio's layout (converted to the record's layout by the caller)."""

    q: np.ndarray  # (T, nq)
    v: np.ndarray  # (T, nv)
    tau: np.ndarray  # (T, nu)
    wrench: np.ndarray  # (T, nc, 6) on the robot at each contact point, world axes
    active: np.ndarray  # (T, nc) bool
    # Free props' reference poses, name -> (T, 7) (x y z, quaternion w x y z), filled by the task
    # (`PhaseTask.complete_frames`); the record's `prop_poses`.
    prop_poses: dict[str, np.ndarray] = field(default_factory=dict)


def contact_wrenches(data, problem: Problem, node_contacts: tuple[str, ...], out: np.ndarray) -> None:
    """Write the world-axis wrench of each active contact of a node's data into `out` (nc, 6): the
    force of a running node, the impulse (N s) of an impulse node.

    Crocoddyl keeps 6D contact forces in the contact frame (LOCAL) and 3D ones in world-aligned axes.
    """
    out[:] = 0.0
    if hasattr(data, "differential"):
        diff = data.differential
        dd = (diff if hasattr(diff, "multibody") else diff[0]).multibody  # Runge-Kutta: the first stage
        forces = dd.contacts.contacts
    else:
        dd = data.multibody
        forces = dd.impulses.impulses
    for name in node_contacts:
        f = forces[name].f.vector
        i = problem.contact_names.index(name)
        if problem.flat[name]:
            R = dd.pinocchio.oMf[problem.frame_ids[name]].rotation
            out[i, :3] = R @ f[:3]
            out[i, 3:] = R @ f[3:]
        else:
            out[i, :3] = f[:3]


def _active(problem: Problem, node_contacts: tuple[str, ...]) -> list[bool]:
    return [name in node_contacts for name in problem.contact_names]


# Per running node: (node index, the node's 5-ms model, its data) -> the node's torque policy,
# (frame index within the node, state) -> torque (clipped to the limits by the caller).
NodePolicy = Callable[[int, np.ndarray], np.ndarray]
PolicyFactory = Callable[[int, object, object], NodePolicy]


def complete(coarse: Problem, cones: ContactCones | None, policy_for_node: PolicyFactory) -> Frames:
    """Frames at the frame period on the coarse problem's own dynamics, torques from a policy.

    Each running node's contact dynamics (its contacts and Baumgarte terms, without costs) is
    integrated in 5-ms semi-implicit Euler steps under the node's policy, torques clipped to the
    limits; impulse nodes are applied at their instants. Where the torque would push a contact
    wrench out of its cone, the closest torque whose wrenches are inside is used (`ContactCones`).
    A contact that touches down is held where the foot actually is at that instant (its Baumgarte
    reference is moved there), so the contact never pulls the foot towards a foothold it missed by
    a few millimetres: this changes the problem's contact references, so extract anything else from
    the problem first. Every frame is then an exact step of the optimizer's dynamics.

    A policy with a compiled form (`compiled_law`: the tracking law, `tracking.NodeTracking`) runs
    its node's frames in C++ where the compiled parts load (`_compiled_node`), with the same result
    to round-off.
    """
    shooting = coarse.shooting
    state = shooting.runningModels[0].state
    pm = state.pinocchio
    nq = pm.nq
    frames = _empty_frames(coarse, nq, pm.nv, int(round(coarse.duration / FRAME_DT)) + 1)
    limit = pm.effortLimit[6:]
    no_costs = crocoddyl.CostModelSum(state, coarse.nu)
    x = shooting.x0.copy()
    frame, u = 0, None
    for k, (node, model, data) in enumerate(zip(coarse.nodes[:-1], shooting.runningModels, shooting.runningDatas)):
        if node.kind == "impulse":
            model.calc(data, x)
            x = data.xnext.copy()
            _anchor_touchdowns(coarse, k, x)
            continue
        differential = model.differential  # the contacts are shared: anchoring applies here too
        # The node's own state: a phase carrying a payload has its own model (`ProblemBuilder._carrying`).
        own = differential.state
        dynamics = crocoddyl.DifferentialActionModelContactFwdDynamics(
            own, differential.actuation, differential.contacts,
            no_costs if own is state else crocoddyl.CostModelSum(own, coarse.nu), 0.0, True
        )
        fine = crocoddyl.IntegratedActionModelEuler(dynamics, FRAME_DT)
        fine_data = fine.createData()
        policy = policy_for_node(k, fine, fine_data)
        active = _active(coarse, node.contacts)
        count = int(round(node.dt / FRAME_DT))
        native = load_native() if hasattr(policy, "compiled_law") else None
        if native is not None:
            x = _compiled_node(native, policy.compiled_law(), coarse, node, fine, fine_data, cones, limit, x,
                               frames, frame, count)
            frames.active[frame : frame + count] = active
            frame += count
            u = frames.tau[frame - 1].copy()
            continue
        for i in range(count):
            u = np.clip(policy(i, x), -limit, limit)
            fine.calc(fine_data, x, u)
            if cones is not None and node.contacts and not cones.holds(fine_data, node.contacts, node.phase_index):
                u = np.clip(cones.project(fine, fine_data, x, u, node.contacts, limit, node.phase_index), -limit, limit)
                fine.calc(fine_data, x, u)
            frames.q[frame], frames.v[frame], frames.tau[frame] = x[:nq], x[nq:], u
            contact_wrenches(fine_data, coarse, node.contacts, frames.wrench[frame])
            frames.active[frame] = active
            x = fine_data.xnext.copy()
            if not np.isfinite(x).all():
                raise SolverError(f"the 200 Hz frames diverged at t = {node.time:.3f} s")
            frame += 1
    terminal, terminal_data = shooting.terminalModel, shooting.terminalData
    terminal.calc(terminal_data, x, u)
    frames.q[frame], frames.v[frame], frames.tau[frame] = x[:nq], x[nq:], u
    contact_wrenches(terminal_data, coarse, coarse.nodes[-1].contacts, frames.wrench[frame])
    frames.active[frame] = _active(coarse, coarse.nodes[-1].contacts)
    return frames


def _compiled_node(native, law: dict, coarse: Problem, node, fine, fine_data, cones: ContactCones | None,
                   limit: np.ndarray, x: np.ndarray, frames: Frames, frame: int, count: int) -> np.ndarray:
    """A node's frames under a policy's compiled law (`native.track_frames`), the frames whose
    wrenches leave their cones projected here as in `complete`'s loop; the state after the node."""
    nq = frames.q.shape[1]
    x = np.array(x, dtype=float)
    u = np.empty(len(limit))
    limit = np.ascontiguousarray(limit, dtype=float)
    rows = slice(frame, frame + count)
    q, v, tau, wrench = frames.q[rows], frames.v[rows], frames.tau[rows], frames.wrench[rows]
    arrays = {"x": x, "x_ref": law["x_ref"], "u": u, "u_k": law["u_k"], "a_plan": law["a_plan"], "gain": law["gain"],
              "limit": limit, "q": q, "v": v, "tau": tau, "wrench": wrench}
    cone_rows = cone_cols = 0
    if cones is not None and node.contacts:
        arrays["cone"], arrays["lower"], arrays["upper"] = cones.tolerant(node.contacts, node.phase_index)
        cone_rows, cone_cols = arrays["cone"].shape
    for key, a in arrays.items():  # read and written by address
        if not (a.flags.c_contiguous and a.dtype == np.float64) or (key in ("x", "x_ref", "u", "gain", "q", "v", "tau", "wrench")
                                                                     and not a.flags.writeable):
            raise ValueError(f"frame tracking: {key} must be a contiguous float64 array")
    pointers = {key: a.ctypes.data for key, a in arrays.items()}
    contacts = [(name, coarse.contact_names.index(name), bool(coarse.flat[name]), int(coarse.frame_ids[name]))
                for name in node.contacts]
    i = 0
    while True:
        i = native.track_frames(fine, fine_data, law["state"], pointers, i, count, law["kp"], law["kd"], FRAME_DT,
                                contacts, wrench.shape[1], cone_rows, cone_cols)
        if not np.isfinite(x).all():
            raise SolverError(f"the 200 Hz frames diverged at t = {node.time:.3f} s")
        if i == count:
            return x
        # frame i's wrenches left their cones: its torque projected, as `complete`'s loop does
        projected = np.clip(cones.project(fine, fine_data, x, u, node.contacts, limit, node.phase_index), -limit, limit)
        fine.calc(fine_data, x, projected)
        q[i], v[i], tau[i] = x[:nq], x[nq:], projected
        contact_wrenches(fine_data, coarse, node.contacts, wrench[i])
        x[:] = fine_data.xnext
        if not np.isfinite(x).all():
            raise SolverError(f"the 200 Hz frames diverged at t = {node.time:.3f} s")
        i += 1


def rollout(coarse: Problem, solution: Solution, cones: ContactCones | None = None) -> Frames:
    """Frames under the solver's feedback policy u = u_k - K_k (x_ref(t) (-) x), x_ref interpolated
    between the knots (`complete`)."""
    state = coarse.shooting.runningModels[0].state
    pm = state.pinocchio
    xs, us, Ks = solution.xs, solution.us, solution.K

    def policy_for_node(k: int, fine, fine_data) -> NodePolicy:
        steps = int(round(coarse.nodes[k].dt / FRAME_DT))

        def policy(i: int, x: np.ndarray) -> np.ndarray:
            return us[k] - Ks[k] @ state.diff(_interpolate_state(pm, xs[k], xs[k + 1], i / steps), x)

        return policy

    return complete(coarse, cones, policy_for_node)


def _point_normal_frame(problem: Problem, name: str, phase: int | None = None) -> np.ndarray:
    """The rotation whose z axis is the planned normal of point contact `name` in phase `phase` (a
    door's panel turns: each phase has its own), or its first one."""
    phases = problem.phases if phase is None else [problem.phases[phase], *problem.phases]
    for p in phases:
        for c in p.contacts:
            if c.name == name:
                return np.asarray(c.placement.rotation)
    return np.eye(3)


class ContactCones:
    """Friction cones and centre-of-pressure bounds of the contacts, as a rollout enforces them.

    When the feedback torque would push a contact wrench out of its cone, the rollout uses the
    torque closest to it (in torque-limit units) whose wrenches are inside: contact wrenches are
    affine in the torque at a given state, so this is a least-distance problem (solved as NNLS,
    Lawson and Hanson). Torques change only at those frames, and every frame stays an exact step.
    """

    def __init__(self, problem: Problem, robot_feet: dict[str, tuple[float, float]], mu: float):
        self.problem, self.robot_feet, self.mu = problem, robot_feet, mu
        self._rows: dict[tuple[str, int | None], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._stacks: dict[tuple[tuple[str, ...], int | None], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._tolerant: dict[tuple[tuple[str, ...], int | None], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def rows(self, name: str, phase: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The cone's rows (A, lb, ub) of contact `name` in phase `phase` (built once)."""
        key = (name, None if self.problem.flat[name] or phase is None else phase)
        if key not in self._rows:
            if self.problem.flat[name]:
                length, width = self.robot_feet[name]
                cone = crocoddyl.WrenchCone(np.eye(3), self.mu, np.array([length, width]), 4, True, 0.0)
            else:  # a point contact's force is in world axes: the cone's normal is its placement's z
                cone = crocoddyl.FrictionCone(_point_normal_frame(self.problem, name, key[1]), self.mu, 4, True, 0.0)
            self._rows[key] = (np.array(cone.A), np.array(cone.lb), np.array(cone.ub))
        return self._rows[key]

    def _stack(self, contacts, phase: int | None = None):
        """The block-diagonal rows (A, lb, ub) of several contacts, built once per contact set and
        phase (every frame of a node asks for the same)."""
        key = (tuple(contacts), phase)
        if key not in self._stacks:
            self._stacks[key] = self._build_stack(contacts, phase)
        return self._stacks[key]

    def _build_stack(self, contacts, phase: int | None):
        blocks, lower, upper = [], [], []
        for name in contacts:
            A, lb, ub = self.rows(name, phase)
            blocks.append(A)
            lower.append(lb)
            upper.append(ub)
        size = sum(b.shape[1] for b in blocks)
        A = np.zeros((sum(b.shape[0] for b in blocks), size))
        r = c = 0
        for b in blocks:
            A[r : r + b.shape[0], c : c + b.shape[1]] = b
            r, c = r + b.shape[0], c + b.shape[1]
        return A, np.concatenate(lower), np.concatenate(upper)

    def _forces(self, data, contacts) -> np.ndarray:
        forces = data.differential.multibody.contacts.contacts
        # a 6D contact's wrench, a 3D one's force (the rows of its cone)
        return np.concatenate([forces[n].f.vector[: 6 if self.problem.flat[n] else 3] for n in contacts])

    def tolerant(self, contacts, phase: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rows (A, lb, ub) that `holds` checks, bounds widened by its tolerance (built once)."""
        key = (tuple(contacts), phase)
        if key not in self._tolerant:
            A, lb, ub = self._stack(contacts, phase)
            self._tolerant[key] = (np.ascontiguousarray(A, dtype=float), lb - 1e-9, ub + 1e-9)
        return self._tolerant[key]

    def holds(self, data, contacts, phase: int | None = None) -> bool:
        A, lower, upper = self.tolerant(contacts, phase)
        r = A @ self._forces(data, contacts)
        return bool((r <= upper).all() and (r >= lower).all())

    def project(self, model, data, x, u, contacts, limits, phase: int | None = None) -> np.ndarray:
        model.differential.calcDiff(data.differential, x, u)
        A, lb, ub = self._stack(contacts, phase)
        f0 = self._forces(data, contacts)
        G = A @ data.differential.df_du  # cone rows per unit torque
        r0 = A @ f0
        if not (np.all(np.isfinite(G)) and np.all(np.isfinite(r0))):
            return u
        finite_ub, finite_lb = np.isfinite(ub), np.isfinite(lb)
        # P du <= e, in z = du / limits: least distance to the polyhedron {P' z <= e}
        P = np.vstack([G[finite_ub], -G[finite_lb]]) * limits
        e = np.concatenate([ub[finite_ub] - r0[finite_ub], r0[finite_lb] - lb[finite_lb]])
        E = np.vstack([-P.T, -e[None, :]])  # LDP as NNLS: min |E w - [0..0, 1]|, w >= 0
        target = np.zeros(E.shape[0])
        target[-1] = 1.0
        w, _ = nnls(E, target, maxiter=50 * E.shape[1])
        residual = E @ w - target
        if abs(residual[-1]) < 1e-12:  # empty polyhedron: keep the feedback torque
            return u
        z = -residual[:-1] / residual[-1]
        return u + z * limits


def _anchor_touchdowns(problem: Problem, k: int, x: np.ndarray) -> None:
    """Move the contact references of the contacts starting at impulse node k to where they are."""
    shooting = problem.shooting
    impulse_data = shooting.runningDatas[k]
    oMf = impulse_data.multibody.pinocchio.oMf
    for name in problem.nodes[k].touching:
        placement = oMf[problem.frame_ids[name]].copy()
        models = list(shooting.runningModels[k + 1 :]) + [shooting.terminalModel]
        shift = None  # a point contact's references all move by its miss (a sliding one keeps its path)
        for node, model in zip(problem.nodes[k + 1 :], models):
            if node.kind == "impulse":  # another contact touching down: this one stays
                continue
            if name not in node.contacts:
                break
            contact = model.differential.contacts.contacts[name].contact
            if problem.flat[name]:
                contact.reference = placement
            else:
                if shift is None:
                    shift = placement.translation - contact.reference
                contact.reference = contact.reference + shift


def _interpolate_state(pm: pin.Model, xa: np.ndarray, xb: np.ndarray, s: float) -> np.ndarray:
    nq = pm.nq
    return np.concatenate([pin.interpolate(pm, xa[:nq], xb[:nq], s), (1 - s) * xa[nq:] + s * xb[nq:]])


def interpolate(coarse: Problem, solution: Solution) -> Frames:
    """Frames between the knots: states interpolated on the configuration manifold, torques and
    contact wrenches held from the knot that starts each interval."""
    shooting = coarse.shooting
    pm = shooting.runningModels[0].state.pinocchio
    nq = pm.nq
    xs = solution.xs
    count = int(round(coarse.duration / FRAME_DT)) + 1
    frames = _empty_frames(coarse, nq, pm.nv, count)
    running = [i for i, n in enumerate(coarse.nodes) if n.kind == "running"]
    j, evaluated = 0, None
    wrench = np.zeros(frames.wrench.shape[1:])
    for frame in range(count - 1):
        t = frame * FRAME_DT
        while j + 1 < len(running) and coarse.nodes[running[j + 1]].time <= t + 1e-9:
            j += 1
        k = running[j]
        node = coarse.nodes[k]
        x = _interpolate_state(pm, xs[k], xs[k + 1], (t - node.time) / node.dt)
        frames.q[frame], frames.v[frame], frames.tau[frame] = x[:nq], x[nq:], solution.us[k]
        if k != evaluated:  # each node evaluated just before its forces are read: nodes may share a scratch
            data = shooting.runningDatas[k]
            shooting.runningModels[k].calc(data, xs[k], solution.us[k])
            contact_wrenches(data, coarse, node.contacts, wrench)
            evaluated = k
        frames.wrench[frame] = wrench
        frames.active[frame] = _active(coarse, node.contacts)
    last, u_last = coarse.nodes[-1], solution.us[running[-1]]
    shooting.terminalModel.calc(shooting.terminalData, xs[-1], u_last)
    frames.q[-1], frames.v[-1], frames.tau[-1] = xs[-1][:nq], xs[-1][nq:], u_last
    contact_wrenches(shooting.terminalData, coarse, last.contacts, frames.wrench[-1])
    frames.active[-1] = _active(coarse, last.contacts)
    return frames


def _empty_frames(problem: Problem, nq: int, nv: int, count: int) -> Frames:
    nc = len(problem.contact_names)
    return Frames(
        q=np.empty((count, nq)),
        v=np.empty((count, nv)),
        tau=np.zeros((count, problem.nu)),
        wrench=np.zeros((count, nc, 6)),
        active=np.zeros((count, nc), bool),
    )
