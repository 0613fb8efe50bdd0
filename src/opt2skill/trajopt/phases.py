"""Phase-based problems: a motion is a sequence of phases, each with its own contacts and costs.

Every task (walking, stairs, pickup, reaching with an elbow contact, wiping, door pushing) describes
its motion as `Phase`s; `ProblemBuilder` turns them into a Crocoddyl shooting problem:

- one running node per solver step, with contact forward dynamics
  (`DifferentialActionModelContactFwdDynamics`) of exactly the phase's contacts (one contact model
  per phase: deactivating contacts inside one model stops FDDP, crocoddyl issue 1250);
- an impulse node where a contact starts (the touchdown impact), when impacts are enabled; the
  fixed contacts that hold through it are in its impulse model too (they are rigid at the impact,
  as in a real one: without them the impact's velocity change moved a stance foot, which its
  Baumgarte term then pulled back; sliding contacts stay out, an impulse would stop them);
- a terminal node with the last phase's contacts;
- at every node the task's costs (`Phase.costs`) plus the physical limits every task shares: wrench
  cone (friction and centre of pressure) of each stance contact, joint position and velocity ranges.

Building without costs (`with_costs=False`) gives the same dynamics for rollouts at another step.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import crocoddyl
import numpy as np
import pinocchio as pin

from opt2skill.data.record import FRAME_DT
from opt2skill.errors import ConfigError
from opt2skill.model.robot import Robot
from opt2skill.trajopt.costs import Terms
from opt2skill.trajopt.integrator import matched_euler, share_scratch, single_threaded
from opt2skill.trajopt.native import load_simd as load_native  # the derivatives' products compiled for AVX2/FMA
from opt2skill.trajopt.posture import Posture
from opt2skill.trajopt.squeeze import SqueezeActuation
from opt2skill.trajopt.settings import ContactSettings, FeasibilityWeights


@dataclass(frozen=True)
class Contact:
    """An active contact: an end effector held at a planned placement (the Baumgarte reference).

    `flat` contacts (feet) are 6D with a wrench cone over the sole; others are 3D point contacts
    with a friction cone whose normal is the placement's z axis.

    A point contact may slide along a planned `path` (a hand wiping a desk): t -> its point's
    position, velocity and acceleration (world). Each node's Baumgarte reference is then
    p + (Kd v + a) / Kp, so the contact's acceleration law a_c = -Kp (x - p_ref) - Kd x' becomes
    a(t) - Kp (x - p) - Kd (x' - v): the point follows the path exactly, the surface's forces
    (normal and friction) are the constraint's. `min_normal_force` replaces the contact settings'
    lower bound of its cone (a light touch of 0 N, where the feet keep 10 N).
    """

    name: str
    placement: pin.SE3
    flat: bool = True
    path: Callable[[float], tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
    min_normal_force: float | None = None


@dataclass(frozen=True)
class Knot:
    """Where a node sits, handed to the task's cost function."""

    time: float  # absolute time of the node (s)
    phase_index: int
    phase_time: float  # time since the phase started
    kind: str  # "running", "impulse" or "terminal"


CostFunction = Callable[[Knot, Terms], list]


@dataclass
class Phase:
    duration: float
    contacts: tuple[Contact, ...]
    costs: CostFunction  # (knot, terms) -> list of (name, cost model, weight)
    label: str = ""
    # Point masses the robot carries in this phase: (end effector, kg), e.g. half a held box at each
    # hand. The phase's dynamics is the robot's with these masses at those points (docs/trajopt.md).
    payload: tuple[tuple[str, float], ...] = ()
    # N each of the payload's two points presses on what it holds (an equal and opposite pair along
    # the line between them, so friction can hold the object): the arms' torques hold it
    # (`trajopt.squeeze`), so the solver's torque bounds see it.
    squeeze: float = 0.0
    # The phase's own posture regularization (`PhaseTask` adds it), instead of the task's: the
    # steps after a pickup need the walk's softer legs, the pickup its stiff ones.
    posture: Posture | None = None


@dataclass(frozen=True)
class Node:
    time: float
    dt: float  # 0 for impulse and terminal nodes
    kind: str
    phase_index: int
    contacts: tuple[str, ...]  # active contacts (impulse nodes: those in the impulse model)
    touching: tuple[str, ...] = ()  # impulse nodes: the contacts that touch down


@dataclass
class Problem:
    """A shooting problem and the timeline of its nodes (running and impulse, then terminal)."""

    shooting: crocoddyl.ShootingProblem
    nodes: list[Node]
    dt: float
    contact_names: tuple[str, ...]  # every contact that appears, in a fixed order
    frame_ids: dict[str, int]  # Pinocchio frame of each contact
    flat: dict[str, bool]  # 6D (True) or 3D contact
    nu: int
    phases: list[Phase] = field(repr=False, default_factory=list)
    # node index -> a terminal model with that node's contacts and costs (ends of receding windows)
    end_model: Callable[[int], object] | None = field(repr=False, default=None)

    @property
    def duration(self) -> float:
        return self.nodes[-1].time


def contact_dynamics(state, actuation, contacts, costs):
    """Crocoddyl's contact forward dynamics (no damping, the forces' derivatives on), the matrix products
    of its derivatives compiled for AVX2 and FMA where this CPU has them (`trajopt.native`; the same
    derivatives to round-off)."""
    compiled = load_native()
    model = compiled.ContactFwdDynamics if compiled is not None else crocoddyl.DifferentialActionModelContactFwdDynamics
    return model(state, actuation, contacts, costs, 0.0, True)


class ProblemBuilder:
    """Builds Crocoddyl problems from phases for one robot with one set of contact/limit settings."""

    def __init__(self, robot: Robot, contact: ContactSettings, feasibility: FeasibilityWeights):
        self.robot = robot
        self.contact = contact
        self.feasibility = feasibility
        self.state = crocoddyl.StateMultibody(robot.pin_model)
        self.actuation = crocoddyl.ActuationModelFloatingBase(self.state)
        self.nu = self.actuation.nu
        self._limit_bounds = self._joint_limit_bounds()
        self._payload_states: dict = {}
        self._scratch: dict = {}  # differential datas shared by the matched nodes of one structure

    def frame_id(self, contact_name: str) -> int:
        return self.robot.pin_frame_id(self.robot.config.end_effectors[contact_name])

    def build(
        self, phases: list[Phase], x0: np.ndarray, dt: float, *, with_costs: bool = True, integrator: str = "euler"
    ) -> Problem:
        if not phases:
            raise ConfigError("a problem needs at least one phase")
        nodes: list[Node] = []
        models = []
        self._scratch = {}  # a problem's nodes share scratches with each other, not with older problems'
        t = 0.0
        previous: set[str] = set()
        held: set[str] = set()
        phase_start = []
        for index, phase in enumerate(phases):
            phase_start.append(t)
            durations = self._discretize(phase, index, dt)
            names = {c.name for c in phase.contacts}
            starting = [c for c in phase.contacts if c.name not in previous]
            if index > 0 and starting and self.contact.impacts:
                knot = Knot(t, index, 0.0, "impulse")
                # a sliding contact moves through the impact: an impulse would stop it
                rigid = [c for c in phase.contacts if c.name not in previous
                         or (self.contact.impacts_hold and c.name in held and c.path is None)]
                models.append(self._impulse_model(rigid, phase, knot, with_costs))
                nodes.append(Node(t, 0.0, "impulse", index, tuple(sorted(c.name for c in rigid)),
                                  tuple(c.name for c in starting)))
            offset = 0.0
            for node_dt in durations:
                knot = Knot(t + offset, index, offset, "running")
                models.append(self._running_model(phase, knot, node_dt, with_costs, integrator))
                nodes.append(Node(knot.time, node_dt, "running", index, tuple(sorted(names))))
                offset += node_dt
            t = round((t + phase.duration) / FRAME_DT) * FRAME_DT
            # A hand that held a payload already touches what it puts down: no impact when it becomes
            # a contact again (the record keeps it active throughout).
            previous = names | {name for name, _ in phase.payload}
            held = names  # contacts that hold through the next phase's impacts
        last = phases[-1]
        knot = Knot(t, len(phases) - 1, last.duration, "terminal")
        terminal = self._running_model(last, knot, 0.0, with_costs)
        nodes.append(Node(t, 0.0, "terminal", len(phases) - 1, tuple(sorted(c.name for c in last.contacts))))
        flat: dict[str, bool] = {}
        for phase in phases:
            for c in phase.contacts:
                if flat.setdefault(c.name, c.flat) != c.flat:
                    raise ConfigError(f"contact '{c.name}' is flat in one phase and a point in another")
        shooting = single_threaded(crocoddyl.ShootingProblem(np.asarray(x0, dtype=float), models, terminal))

        def end_model(i: int):
            node = nodes[i]
            phase = phases[node.phase_index]
            start = node.time - (node.time - phase_start[node.phase_index])
            knot = Knot(node.time, node.phase_index, node.time - start, "running")
            return self._running_model(phase, knot, 0.0, with_costs, integrator)

        return Problem(
            shooting=shooting,
            nodes=nodes,
            dt=dt,
            contact_names=tuple(flat),
            frame_ids={name: self.frame_id(name) for name in flat},
            flat=flat,
            nu=self.nu,
            phases=list(phases),
            end_model=end_model,
        )

    @staticmethod
    def _discretize(phase: Phase, index: int, dt: float) -> list[float]:
        """Node durations of a phase: about `dt` each, whole frame periods each, at least one node.

        Phase durations must be multiples of the frame period, so every phase switch (and impulse)
        and every node falls on a 200 Hz frame.
        """
        frames = phase.duration / FRAME_DT
        if phase.duration <= 0 or abs(frames - round(frames)) > 1e-6:
            raise ConfigError(
                f"phase {index} ('{phase.label}') lasts {phase.duration:g} s, "
                f"not a positive multiple of the frame period {FRAME_DT:g} s"
            )
        frames = int(round(frames))
        # Integer arithmetic: the same phase length must always give the same nodes (a float tie
        # such as 0.105 / 0.03 = 3.4999... or 3.5000... broke the stride periodicity of walks).
        per_node = max(1, int(round(dt / FRAME_DT)))
        steps = min(max(1, (2 * frames + per_node) // (2 * per_node)), frames)
        sizes = [frames // steps + (1 if i < frames % steps else 0) for i in range(steps)]
        return [size * FRAME_DT for size in sizes]

    # -- nodes ---------------------------------------------------------------------------------

    def _running_model(self, phase: Phase, knot: Knot, dt: float, with_costs: bool, integrator: str = "euler"):
        state, actuation = self._carrying(phase.payload, phase.squeeze)
        contacts = crocoddyl.ContactModelMultiple(state, self.nu)
        for c in phase.contacts:
            contacts.addContact(c.name, self._contact_model(c, state, knot.time))
        costs = crocoddyl.CostModelSum(state, self.nu)
        if with_costs:
            terms = Terms(state, self.nu, self.robot)
            for name, cost, weight in phase.costs(knot, terms):
                costs.addCost(name, cost, weight)
            self._add_limits(costs, phase.contacts, terms, knot.kind if dt > 0 else "terminal")
        dam = contact_dynamics(state, actuation, contacts, costs)
        if with_costs:  # the optimizer keeps a torque margin for feedback; rollouts use the full range
            limit = self.robot.config.torque_limit * self.feasibility.torque_limit_scale
            dam.u_lb, dam.u_ub = -limit, limit
        substeps = int(round(dt / FRAME_DT))
        if integrator == "euler" or dt == 0.0 or (integrator == "matched" and substeps == 1):
            return crocoddyl.IntegratedActionModelEuler(dam, dt)
        if integrator == "matched":
            model = matched_euler(dam, dt, substeps)
            share_scratch(model, self._scratch, (tuple(sorted(phase.payload)), float(phase.squeeze)))
            return model
        rk = {"rk2": crocoddyl.RKType.two, "rk3": crocoddyl.RKType.three, "rk4": crocoddyl.RKType.four}[integrator]
        return crocoddyl.IntegratedActionModelRK(dam, rk, dt)

    def _impulse_model(self, rigid: list[Contact], phase: Phase, knot: Knot, with_costs: bool):
        state, _ = self._carrying(phase.payload, phase.squeeze)
        impulses = crocoddyl.ImpulseModelMultiple(state)
        for c in rigid:
            fid = self.frame_id(c.name)
            if c.flat:
                impulse = crocoddyl.ImpulseModel6D(state, fid, pin.LOCAL)
            else:
                impulse = crocoddyl.ImpulseModel3D(state, fid, pin.LOCAL_WORLD_ALIGNED)
            impulses.addImpulse(c.name, impulse)
        costs = crocoddyl.CostModelSum(state, 0)
        if with_costs:
            terms = Terms(state, 0, self.robot)
            for name, cost, weight in phase.costs(knot, terms):
                costs.addCost(name, cost, weight)
        model = crocoddyl.ActionModelImpulseFwdDynamics(state, impulses, costs)
        model.JMinvJt_damping = 1e-12
        model.r_coeff = 0.0  # fully plastic touchdown: the contact point stops
        return model

    def _contact_model(self, c: Contact, state, t: float):
        fid = self.frame_id(c.name)
        kp, kd = self.contact.baumgarte_kp, self.contact.baumgarte_kd
        gains = np.array([kp, kd])
        if c.flat:
            return crocoddyl.ContactModel6D(state, fid, c.placement, pin.LOCAL, self.nu, gains)
        point = c.placement.translation
        if c.path is not None:
            if kp <= 0:
                raise ConfigError(f"contact '{c.name}' slides along a path: it needs contact.baumgarte_kp > 0")
            p, v, a = c.path(t)
            point = np.asarray(p, float) + (kd * np.asarray(v, float) + np.asarray(a, float)) / kp
        return crocoddyl.ContactModel3D(state, fid, point, pin.LOCAL_WORLD_ALIGNED, self.nu, gains)

    def _carrying(self, payload: tuple[tuple[str, float], ...], squeeze: float = 0.0):
        """State and actuation of the robot carrying point masses at end effectors (cached), the
        two points squeezing what they hold with `squeeze` N (`trajopt.squeeze`).

        A point mass m at a point p of a body adds m J_p^T (a_p - g) to the equations of motion, so
        the robot-only dynamics of the same motion balances with the force m (g - a_p) at p: that
        is the held object's force on the robot the record stores (no rotational inertia, exact)."""
        if not payload:
            if squeeze:
                raise ConfigError("a phase's squeeze needs a payload held at two points")
            return self.state, self.actuation
        key = (tuple(sorted(payload)), float(squeeze))
        if key not in self._payload_states:
            model = pin.Model(self.robot.pin_model)
            for name, mass in key[0]:
                frame = model.frames[self.frame_id(name)]
                lever = frame.placement.translation
                model.inertias[frame.parentJoint] = model.inertias[frame.parentJoint] + pin.Inertia(
                    float(mass), lever, np.zeros((3, 3)))
            state = crocoddyl.StateMultibody(model)
            if squeeze:
                if len(payload) != 2:
                    raise ConfigError(f"a squeeze needs a payload held at two points, not {len(payload)}")
                actuation = SqueezeActuation(state, tuple(self.frame_id(name) for name, _ in payload), squeeze)
            else:
                actuation = crocoddyl.ActuationModelFloatingBase(state)
            self._payload_states[key] = (model, state, actuation)
        _, state, actuation = self._payload_states[key]
        return state, actuation

    # -- limits shared by every task --------------------------------------------------------------

    def _add_limits(self, costs, contacts: tuple[Contact, ...], terms: Terms, kind: str) -> None:
        weights = self.feasibility
        if weights.joint_limits > 0:
            lb, ub = self._limit_bounds
            costs.addCost("joint_limits", terms.state_bounds(lb, ub), weights.joint_limits)
        if weights.wrench_cone <= 0 or kind == "terminal":
            return
        mu = self.robot.config.friction_coefficient * self.contact.friction_scale
        for c in contacts:
            fid = self.frame_id(c.name)
            if c.flat:
                foot = self._foot(c.name)
                box = np.array([2 * foot.half_length, 2 * foot.half_width]) * self.contact.cop_scale
                cost = terms.wrench_cone(fid, mu, box, self.contact.min_normal_force)
            else:
                least = self.contact.min_normal_force if c.min_normal_force is None else c.min_normal_force
                cost = terms.friction_cone(fid, c.placement.rotation, mu, least)
            costs.addCost(f"{c.name}_cone", cost, weights.wrench_cone)

    def _foot(self, contact_name: str):
        site = self.robot.config.end_effectors[contact_name]
        for foot in self.robot.config.feet:
            if foot.sole_site == site:
                return foot
        raise ConfigError(f"flat contact '{contact_name}' is not a foot of robot '{self.robot.name}'")

    def _joint_limit_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds on the state residual x - x_neutral: joint ranges (with margin) and speed limits."""
        pm = self.robot.pin_model
        w = self.feasibility
        nv = pm.nv
        lb = np.full(2 * nv, -np.inf)
        ub = np.full(2 * nv, np.inf)
        lb[6:nv] = pm.lowerPositionLimit[7:] + w.joint_limit_margin
        ub[6:nv] = pm.upperPositionLimit[7:] - w.joint_limit_margin
        lb[nv + 6 :] = -pm.velocityLimit[6:] * w.velocity_limit_scale
        ub[nv + 6 :] = pm.velocityLimit[6:] * w.velocity_limit_scale
        return lb, ub
