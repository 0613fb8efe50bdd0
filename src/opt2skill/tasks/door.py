"""Door pushing while walking: both hands push a hinged door open, its spring and damper resisting,
while the robot walks through the doorway.

The plan. The robot stands `distance` m in front of the closed door (a `Door` prop: a panel on a
vertical hinge to the robot's left, closed by a spring and a damper). It stands, reaches both hands
to the panel (`timing.reach`, then `timing.approach` onto it) at `hand_height`, `hand_spacing` apart,
their middle in front of the robot's centre of mass, `lever` m from the hinge. Then it walks: the
locomotion skill's phases (`skills.locomotion.locomotion_phases` along a `skills.gait` plan) with
both hands on the panel at every node.

The hands do not move on the panel; the robot turns with the door. The walk is a turn about the
hinge: forward speed `lever` * w, sideways speed -(the hinge's distance ahead) * w, yaw rate w, all
under the gait's one velocity envelope, so the planned CoM path is an arc about the hinge and the
planned heading is the door's angle. Facing the panel all along, the robot keeps the hands at one
place in front of its torso and its body at one distance from the panel (clear of it, no wall or
frame in the scene), and it ends past the door's closed plane. The door's angle follows from the walk
(the heading), the hands' paths from the angle: each hand is a point contact (friction cone along
the panel's normal, `skills.manipulation`) sliding along the arc its point of the panel describes
(`Contact.path`), its cone's normal that of the panel in the middle of each phase.

The door's resistance: the hinge torque its dynamics needs along the planned angle,
tau = stiffness * angle + damping * rate + inertia * acceleration (`Door.hinge_torque`), is shared
equally by the two hands (each tau / 2 over its lever arm), normal to the panel. The optimizer pulls
each hand's contact force to that (`weights.force`, as the wiping task pulls its hand to a
prescribed force), inside the friction cone; the record's hand forces are the solver's. The
record's door pose (`prop_poses["door"]`) is the planned angle.

Checks: the hands' forces in the robot's friction cone about the panel's normal (`hand_friction`,
N); the hinge torque the recorded hand forces exert against the door's dynamics (`torque_balance`,
its RMS, and `torque_balance_max`, N m); the robot's body (the hands apart) out of the panel at every tenth frame
(`body_contacts`); and the optimizer's feedback expert in MuJoCo with the real door (spring, damper,
inertia) must open it as planned: its hinge angle within `hinge_error` rad of the reference's at
every frame, until the end.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import mujoco
import numpy as np
import pinocchio as pin

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.errors import ConfigError
from opt2skill.scene.description import Scene
from opt2skill.scene.props import Door
from opt2skill.tasks import TaskInfo
from opt2skill.trajopt.config import require
from opt2skill.trajopt.params import Param, ParamSpace
from opt2skill.trajopt.phase_task import PhaseTask, Plan
from opt2skill.trajopt.phases import Contact, Knot, Phase, Problem
from opt2skill.trajopt.posture import Posture
from opt2skill.trajopt.settings import ContactSettings, SolverSettings
from opt2skill.trajopt.skills.desk import Stand, StandingCosts
from opt2skill.trajopt.skills.gait import GaitPlan, GaitSpec, plan_gait
from opt2skill.trajopt.skills.locomotion import LocomotionWeights, com_xy, locomotion_phases, solve_walk, stand_footholds
from opt2skill.trajopt.skills.manipulation import HandPath, contact_radius, normal_frame
from opt2skill.trajopt.skills.stride_guess import RecedingSettings
from opt2skill.trajopt.solver import Solution
from opt2skill.trajopt.task_config import TaskConfig

HANDS = ("left_hand", "right_hand")
DOOR = "door"

PARAMS = (
    Param("distance", allowed=(0.4, 0.6), default_range=(0.44, 0.5), unit="m", help="the door's face ahead of the base"),
    Param("angle", allowed=(0.3, 1.4), default_range=(1.0, 1.2), unit="rad", help="how far the door is pushed open"),
    Param("door_mass", allowed=(1.0, 40.0), default_range=(4.0, 12.0), unit="kg", help="the door panel's mass"),
    Param("stiffness", allowed=(0.0, 30.0), default_range=(3.0, 10.0), unit="N m/rad", help="the closing spring"),
    Param("damping", allowed=(0.0, 15.0), default_range=(1.0, 4.0), unit="N m s/rad", help="the hinge's damper"),
    Param("steps", allowed=(4, 14), default_range=(8.51, 10.49), unit="", help="number of steps, rounded to an integer"),
    Param("step_duration", allowed=(0.35, 0.7), default_range=(0.45, 0.5), unit="s", help="one step (gait period / 2)"),
)


@dataclass(frozen=True)
class DoorTiming:
    """Seconds of each phase before the walk (multiples of the 5-ms frame)."""

    stand: float = 0.3
    reach: float = 1.0  # hands from home to just in front of the panel
    approach: float = 0.4  # onto the panel
    settle: float = 0.4  # on the door, before the first step

    def check(self) -> None:
        require(all(0.005 <= v <= 5.0 for v in vars(self).values()), "timing: every phase must last 0.005 to 5 s")


@dataclass(frozen=True)
class DoorWeights:
    hands: float = 1e4  # hand positions along their paths (free hands)
    touch: float = 1e6  # a hand where it touches the panel (impulse node)
    force: float = 1e2  # each hand's contact force towards the door's share (N^-2); 1e3 stalled the solve
    com: float = 1e3  # CoM over the middle of the feet (standing)
    base_orientation: float = 1e3  # upright (standing)
    # On the generalized accelerations at the walk's running nodes (as the box tasks'): without it
    # the arms' torques jumped by 20 N m from one node to the next, the hands' forces with them.
    acceleration: float = 0.1

    def check(self) -> None:
        require(all(v >= 0 for v in vars(self).values()), "door weights must be >= 0")


@dataclass(frozen=True)
class DoorThresholds:
    hand_friction: float = 1.0  # N, largest hand force outside the friction cone about the panel's normal
    # N m, |hinge torque of the hand forces - the door's dynamics| over the frames both hands push:
    # RMS, and largest (the solver's force is a cost: it deviates by 2 to 3 N m for a few frames
    # where a foot lifts off, 0.2 N m in the median; docs/trajopt.md)
    torque_balance: float = 1.0
    torque_balance_max: float = 4.0
    hinge_error: float = 0.1  # rad, largest |expert's hinge angle in MuJoCo - reference's|
    body_contacts: float = 0.5  # frames (of every tenth) where the robot's body, hands apart, touches the panel

    def check(self) -> None:
        require(all(v > 0 for v in vars(self).values()), "door thresholds must be > 0")


@dataclass(frozen=True)
class DoorPushConfig(TaskConfig):
    door_width: float = 0.9  # m, hinge to free edge
    door_height: float = 2.0  # m
    door_thickness: float = 0.04  # m
    door_friction: float = 0.7  # of the panel's faces (the robot's own mu)
    hand_height: float = 1.0  # m, where the hands press on the panel
    hand_spacing: float = 0.36  # m between the hands along the panel
    lever: float = 0.45  # m from the hinge to the middle of the hands, along the panel
    pregrasp: float = 0.06  # m in front of the panel before touching it
    clearance: float = 0.08  # m, swing-foot apex height
    double_support: float = 0.2  # fraction of a step on both feet
    stand_end: float = 0.8  # s (at least) standing after the last step
    ramp: float = 1.0  # s to reach the turning speed, and to stop
    base_height: float = 0.0  # m, walking base height relative to standing
    max_yaw_rate: float = 0.5  # rad/s the turn about the hinge may ask for at most
    max_lateral_speed: float = 0.3  # m/s sideways, at most
    timing: DoorTiming = field(default_factory=DoorTiming)
    weights: DoorWeights = field(default_factory=DoorWeights)
    thresholds: DoorThresholds = field(default_factory=DoorThresholds)
    walk_weights: LocomotionWeights = field(default_factory=lambda: LocomotionWeights(com_path=1e3))
    # The steps' posture (soft legs and arms, as pickup-then-walk's); standing, `posture`'s stiff legs.
    # No pull on the base's orientation: the start's heading is not the turned walk's.
    walk_posture: Posture = field(default_factory=lambda: Posture(base_orientation=0.0, legs=0.3, leg_velocity=0.3,
                                                                  arms=0.3, base_velocity=1.0))
    posture: Posture = field(default_factory=lambda: Posture(legs=30.0, leg_velocity=3.0, base_velocity=10.0))
    contact: ContactSettings = field(default_factory=lambda: ContactSettings(min_normal_force=10.0))
    # One solve over the whole horizon: receding windows (the walk's) failed with the hands on the
    # panel (a window closed with a gap of 2, the robot collapsing), the whole problem solves.
    receding: RecedingSettings = field(default_factory=lambda: RecedingSettings(enabled=False))
    # The expert's gains from one Riccati pass over the whole motion (pickup then walk's reason).
    solver: SolverSettings = field(default_factory=lambda: SolverSettings(dt=0.02, max_iter=200, reg_init=1e-4,
                                                                          gains="riccati"))

    def check_own(self) -> None:
        require(0.5 <= self.door_width <= 2.0 and 1.2 <= self.door_height <= 3.0 and 0.01 <= self.door_thickness <= 0.15,
                "door_width in [0.5, 2], door_height in [1.2, 3], door_thickness in [0.01, 0.15] m")
        require(0.6 <= self.hand_height <= 1.3, "hand_height must be in [0.6, 1.3] m")
        require(0.1 <= self.hand_spacing <= 0.6, "hand_spacing must be in [0.1, 0.6] m")
        require(self.hand_spacing / 2 + 0.05 <= self.lever <= self.door_width - self.hand_spacing / 2 - 0.05,
                "lever must keep both hands 5 cm inside the panel's edges")
        require(0.02 <= self.pregrasp <= 0.2 and 0.03 <= self.clearance <= 0.2, "pregrasp in [0.02, 0.2] m, clearance in [0.03, 0.2] m")
        require(0.0 <= self.double_support <= 0.5 and self.ramp >= 0 and self.stand_end >= 0.1,
                "double_support in [0, 0.5], ramp >= 0 s, stand_end >= 0.1 s")
        require(-0.2 <= self.base_height <= 0.05, "base_height must be in [-0.2, 0.05] m")
        require(0.0 < self.max_yaw_rate <= 1.0 and 0.0 < self.max_lateral_speed <= 0.5,
                "max_yaw_rate in (0, 1] rad/s, max_lateral_speed in (0, 0.5] m/s")
        for section in (self.timing, self.weights, self.thresholds, self.walk_weights, self.walk_posture, self.receding):
            section.check()


@dataclass(frozen=True)
class DoorMotion:
    """The door's planned angle (rad), rate and acceleration on the 200 Hz grid: the gait's heading."""

    angle: np.ndarray
    rate: np.ndarray
    acceleration: np.ndarray

    @classmethod
    def of(cls, gait: GaitPlan) -> DoorMotion:
        rate = gait.velocity[:, 2]
        return cls(gait.heading - gait.heading[0], rate, np.gradient(rate, FRAME_DT))

    def at(self, t: float) -> tuple[float, float, float]:
        """Angle, rate and acceleration at time t (linear between frames, held after the end)."""
        times = np.arange(len(self.angle)) * FRAME_DT
        return tuple(float(np.interp(t, times, x)) for x in (self.angle, self.rate, self.acceleration))


class DoorPushTask(PhaseTask):
    name = "door_push"
    config_class = DoorPushConfig
    params = PARAMS

    def param_space(self) -> ParamSpace:
        """The parameters; sampling ranges whose widest opening in the fewest, shortest steps needs a
        faster turn than `max_yaw_rate` (or sideways speed) are refused here, before any solve."""
        space = super().param_space()
        r = space.ranges
        corner = {"distance": r["distance"][1], "angle": r["angle"][1], "steps": r["steps"][0],
                  "step_duration": r["step_duration"][0], "door_mass": r["door_mass"][1],
                  "stiffness": r["stiffness"][0], "damping": r["damping"][0]}
        try:
            self.door_motion(corner)
        except ConfigError as exc:
            raise ConfigError(f"the sampling ranges reach a door that cannot be pushed: {exc}") from None
        return space

    # -- the scene -------------------------------------------------------------------------------

    def door(self, params: dict[str, float]) -> Door:
        """The closed door: its face `distance` m ahead of the base, the hinge `lever` m left of
        the middle of the hands (in front of the CoM)."""
        cfg = self.config
        com = com_xy(self.robot, self.robot.stand_q_pin)
        face = self.robot.stand_q_pin[0] + params["distance"]
        return Door(hinge=(float(face + cfg.door_thickness / 2), float(com[1] + cfg.lever)), width=cfg.door_width,
                    height=cfg.door_height, thickness=cfg.door_thickness, mass=params["door_mass"],
                    stiffness=params["stiffness"], damping=params["damping"], friction=cfg.door_friction, name=DOOR)

    def scene(self, params: dict[str, float]) -> Scene:
        return Scene(props=(self.door(params),))

    def levers(self) -> dict[str, float]:
        """Each hand's distance from the hinge along the panel (the left hand is nearer)."""
        half = self.config.hand_spacing / 2
        return {"left_hand": self.config.lever - half, "right_hand": self.config.lever + half}

    @cached_property
    def hand_radius(self) -> dict[str, float]:
        """How far each hand's site lies inside the surface it presses (its collision sphere)."""
        return {h: contact_radius(self.robot, h) for h in HANDS}

    def hand_on_panel(self, door: Door, hand: str, angle) -> np.ndarray:
        """(..., 3) the hand site's position pressing on the panel's front face at hinge angle `angle`."""
        return (door.panel_point(angle, self.levers()[hand], self.config.hand_height)
                + self.hand_radius[hand] * door.face_normal(angle))

    # -- the walk --------------------------------------------------------------------------------

    def turn(self, params: dict[str, float], after: float = 0.0) -> GaitPlan:
        """The walk about the hinge, its first step `timing.settle` after `after` (the hands' touch):
        forward `lever` * w, sideways -(hinge ahead of the CoM) * w, yaw rate w, turning `angle`."""
        cfg = self.config
        feet = stand_footholds(self.robot, self.robot.stand_q_pin)
        com = com_xy(self.robot, self.robot.stand_q_pin)
        ahead = self.robot.stand_q_pin[0] + params["distance"] + cfg.door_thickness / 2 - com[0]
        steps = int(round(params["steps"]))

        def plan(rate: float) -> GaitPlan:
            spec = GaitSpec(speed=cfg.lever * rate, lateral_speed=-ahead * rate, yaw_rate=rate, clearance=cfg.clearance,
                            step_duration=params["step_duration"], double_support=cfg.double_support,
                            stand_start=after + cfg.timing.settle, duration=0.0, stand_end_min=cfg.stand_end,
                            ramp=cfg.ramp, steps=steps)
            return plan_gait(spec, feet, com)

        per_rate = float(plan(1.0).heading[-1])  # the heading is linear in the rate
        rate = params["angle"] / per_rate
        if rate > cfg.max_yaw_rate or ahead * rate > cfg.max_lateral_speed:
            raise ConfigError(f"angle = {params['angle']:g} rad in {steps} steps of {params['step_duration']:g} s "
                              f"needs a turn of {rate:.2f} rad/s and {ahead * rate:.2f} m/s sideways, more than "
                              f"max_yaw_rate {cfg.max_yaw_rate:g} rad/s or max_lateral_speed {cfg.max_lateral_speed:g} m/s: "
                              f"take more or longer steps, or a smaller angle")
        return plan(rate)

    def reach_end(self) -> float:
        T = self.config.timing
        return T.stand + T.reach + T.approach

    def walk_of(self, params: dict[str, float]) -> GaitPlan:
        return self.turn(params, after=self.reach_end())

    def door_motion(self, params: dict[str, float]) -> DoorMotion:
        """The door's planned motion; a door that would swing on ahead of the hands where the turn
        slows down (its inertia beyond what its spring and damper hold back: the hands would have
        to pull) is a ConfigError."""
        motion = DoorMotion.of(self.walk_of(params))
        door = self.door(params)
        torque = door.hinge_torque(motion.angle, motion.rate, motion.acceleration)
        if torque.min() < -1e-6:
            raise ConfigError(f"door_mass = {params['door_mass']:g} kg with stiffness = {params['stiffness']:g} N m/rad "
                              f"and damping = {params['damping']:g} N m s/rad swings on ahead of the hands where the "
                              f"turn slows down (the hands would have to pull with {-torque.min():.2f} N m): take a "
                              f"lighter or stiffer door, or more or longer steps")
        return motion

    def hand_forces(self, door: Door, motion: DoorMotion, t: float) -> dict[str, np.ndarray]:
        """Each hand's planned force on the robot at time t (N, world): half the hinge torque the
        door's dynamics needs, over the hand's lever arm, along the panel's normal (towards the robot)."""
        angle, rate, acceleration = motion.at(t)
        torque = max(float(door.hinge_torque(angle, rate, acceleration)), 0.0)
        normal = door.face_normal(angle)
        return {h: torque / (len(HANDS) * lever) * normal for h, lever in self.levers().items()}

    # -- the plan --------------------------------------------------------------------------------

    def plan(self, params: dict[str, float]) -> Plan:
        cfg, w, T = self.config, self.config.weights, self.config.timing
        door = self.door(params)
        stand = Stand.of(self.robot)
        standing = StandingCosts(self.robot, stand, w.com, w.base_orientation, w.hands)
        home = {h: stand.home[h] for h in HANDS}
        touch = {h: self.hand_on_panel(door, h, 0.0) for h in HANDS}
        before = {h: touch[h] + cfg.pregrasp * door.face_normal(0.0) for h in HANDS}
        phases: list[Phase] = []
        t = 0.0
        for duration, label, start, end in ((T.stand, "stand", home, home), (T.reach, "reach", home, before),
                                            (T.approach, "onto the door", before, touch)):
            path = HandPath(start, end, t, duration)
            phases.append(Phase(duration, stand.feet, self._standing(standing, path), label))
            t += duration
        gait = self.turn(params, after=t)
        motion = self.door_motion(params)
        feet = stand_footholds(self.robot, self.robot.stand_q_pin)
        walking = locomotion_phases(self.robot, gait, feet, cfg.walk_weights, stand.x0[2] + cfg.base_height,
                                    cfg.clearance, after=t)
        touched = t
        for phase in walking:
            phases.append(self._pushing(phase, t, touched, door, motion, touch))
            t += phase.duration
        return Plan(phases=phases, x0=stand.x0, scene=Scene(props=(door,)), context=gait, guess=self._along(gait, stand.x0))

    def _along(self, gait: GaitPlan, x0: np.ndarray):
        """The initial guess: the stand pose carried along the planned turn (the base where the
        planned CoM and heading put it, at rest): from the stand pose held everywhere, 2 of 8 solves
        of the default ranges ended in a bad minimum, the robot hanging on the door."""
        nq = self.robot.pin_model.nq
        com0 = com_xy(self.robot, x0[:nq])

        def guess(problem: Problem) -> list[np.ndarray]:
            out = []
            for node in problem.nodes:
                com, heading, _ = gait.sample(node.time)
                turn = pin.utils.rpyToMatrix(0.0, 0.0, heading)
                x = x0.copy()
                x[:2] = com + turn[:2, :2] @ (x0[:2] - com0)
                x[3:7] = pin.Quaternion(turn @ pin.Quaternion(x0[3:7]).toRotationMatrix()).coeffs()  # x y z w
                out.append(x)
            return out

        return guess

    def _standing(self, standing: StandingCosts, path: HandPath):
        def costs(knot: Knot, terms) -> list:
            return [] if knot.kind == "impulse" else standing.balance(terms) + standing.along(terms, knot, path, HANDS)
        return costs

    def _pushing(self, phase: Phase, start: float, touched: float, door: Door, motion: DoorMotion,
                 touch: dict[str, np.ndarray]) -> Phase:
        """A walking phase with both hands on the panel: each a point contact along its arc, its
        cone's normal the panel's in the middle of the phase, its force pulled to the door's share."""
        w, ee = self.config.weights, self.robot.config.end_effectors
        middle_angle = motion.at(start + phase.duration / 2)[0]
        frame = normal_frame(door.face_normal(middle_angle))
        hands = tuple(Contact(h, pin.SE3(frame, touch[h]), flat=False, path=self._arc(door, motion, h), min_normal_force=0.0)
                      for h in HANDS)
        walk_costs = phase.costs

        def costs(knot: Knot, terms) -> list:
            if knot.kind == "impulse":
                if abs(knot.time - touched) < 1e-9:  # the hands touch the panel where their arcs start
                    return [(f"{h}_touch", terms.translation(ee[h], touch[h]), w.touch) for h in HANDS]
                return walk_costs(knot, terms)
            # the node's force holds over its step: aim at the middle of the step
            middle = knot.time + (self.config.solver.dt / 2 if knot.kind == "running" else 0.0)
            targets = self.hand_forces(door, motion, middle)
            smooth = [("acceleration", terms.acceleration(1.0), w.acceleration)] if knot.kind == "running" else []
            return walk_costs(knot, terms) + smooth + [
                (f"{h}_force", terms.contact_force(self.builder.frame_id(h), targets[h], (1, 1, 1)), w.force) for h in HANDS]

        return dataclasses.replace(phase, contacts=phase.contacts + hands, costs=costs, posture=self.config.walk_posture)

    def _arc(self, door: Door, motion: DoorMotion, hand: str):
        """t -> the hand's position, velocity and acceleration on the turning panel."""
        hinge = np.array([*door.hinge, 0.0])
        z = np.array([0.0, 0.0, 1.0])

        def path(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            angle, rate, acceleration = motion.at(t)
            p = self.hand_on_panel(door, hand, angle)
            r = (p - hinge) * [1.0, 1.0, 0.0]
            return p, rate * np.cross(z, r), acceleration * np.cross(z, r) - rate**2 * r

        return path

    # -- solve and record ------------------------------------------------------------------------

    def optimize(self, problem: Problem, plan: Plan) -> Solution:
        rc = self.config.receding
        if not rc.enabled:
            return super().optimize(problem, plan)
        return solve_walk(problem, self.config.solver, rc, plan.context)

    def complete_frames(self, plan: Plan, problem: Problem, frames, knots: dict):
        """The door's reference pose at every frame: the planned angle."""
        door = plan.scene.prop(DOOR)
        angle = DoorMotion.of(plan.context).angle
        n = len(frames.q)
        frames.prop_poses = {DOOR: door.pose(np.r_[angle, np.full(max(n - len(angle), 0), angle[-1])][:n])}
        return frames

    # -- checks ----------------------------------------------------------------------------------

    def task_errors(self, traj: Trajectory) -> dict[str, dict[str, Any]]:
        th = self.config.thresholds
        door = traj.scene.prop(DOOR)
        angle = door.angle_of(traj.prop_poses[DOOR])
        expert = expert_hinge_angles(self.robot, traj, DOOR)
        hinge_error = float(np.max(np.abs(expert - angle[: len(expert)]), initial=0.0))
        if len(expert) < traj.num_frames:  # the expert fell: the door was not opened as planned
            hinge_error = max(hinge_error, float(np.max(np.abs(angle[len(expert):] - expert[-1]))))
        imbalance = np.abs(torque_imbalance(traj, door))
        return {
            "hand_friction": {"value": door_friction_violation(traj, door, self.robot.config.friction_coefficient),
                              "limit": th.hand_friction, "unit": "N"},
            "torque_balance": {"value": float(np.sqrt(np.mean(imbalance**2))) if len(imbalance) else 0.0,
                               "limit": th.torque_balance, "unit": "N m"},
            "torque_balance_max": {"value": float(np.max(imbalance, initial=0.0)), "limit": th.torque_balance_max,
                                   "unit": "N m"},
            "body_contacts": {"value": float(body_contacts(self.robot, traj, DOOR)), "limit": th.body_contacts, "unit": ""},
            "hinge_error": {"value": hinge_error, "limit": th.hinge_error, "unit": "rad"},
        }


# -- checks on a record ------------------------------------------------------------------------------


def _hands_on(traj: Trajectory) -> list[tuple[int, int, np.ndarray]]:
    names, ee = list(traj.contact_names), list(traj.ee_names)
    return [(names.index(h), ee.index(h), traj.contact_active[:, names.index(h)]) for h in HANDS]


def door_friction_violation(traj: Trajectory, door: Door, mu: float) -> float:
    """Largest max(0, |f_t| - mu f_n, -f_n) (N) of the hands' forces on the robot whenever a hand
    touches the panel, the normal being the panel's at the record's door angle."""
    normal = door.face_normal(door.angle_of(traj.prop_poses[door.name]))
    worst = 0.0
    for c, _, on in _hands_on(traj):
        f, n = traj.contact_wrench[on, c, :3], normal[on]
        fn = np.einsum("ij,ij->i", f, n)
        ft = np.linalg.norm(f - fn[:, None] * n, axis=1)
        worst = max(worst, float(np.max(np.maximum(ft - mu * fn, -fn), initial=0.0)))
    return worst


def hinge_torques(traj: Trajectory, door: Door) -> tuple[np.ndarray, np.ndarray]:
    """(T,) the torque about the hinge the recorded hand forces exert on the door (the opposite of
    theirs on the robot, at the hand sites), and (T,) the torque the door's dynamics needs along the
    record's door angle (`Door.hinge_torque`, rates by central differences)."""
    angle = door.angle_of(traj.prop_poses[door.name])
    rate = np.gradient(angle, FRAME_DT)
    needed = door.hinge_torque(angle, rate, np.gradient(rate, FRAME_DT))
    applied = np.zeros(traj.num_frames)
    hinge = np.array([*door.hinge, 0.0])
    for c, e, on in _hands_on(traj):
        lever = traj.ee_pos[:, e] - hinge
        applied += np.where(on, np.cross(lever, -traj.contact_wrench[:, c, :3])[:, 2], 0.0)
    return applied, needed


def torque_imbalance(traj: Trajectory, door: Door) -> np.ndarray:
    """The hands' hinge torque minus the door's needed torque (N m) at the frames both hands push,
    the first and last two left out (the central differences' ends)."""
    applied, needed = hinge_torques(traj, door)
    both = np.all([on for _, _, on in _hands_on(traj)], axis=0)
    both[:2] = both[-2:] = False
    return (applied - needed)[both]


def expert_hinge_angles(robot, traj: Trajectory, name: str) -> np.ndarray:
    """(F,) the door's hinge angle at each 200 Hz frame while the optimizer's feedback expert plays
    the record in MuJoCo with the real door, until the robot falls (F <= the record's frames); a
    record without the solver's gains is played open loop (reference torques and PD) instead."""
    from opt2skill.data.replay import Replayer
    from opt2skill.scene.build import prop_hinge

    replayer = Replayer(robot, traj)
    at = prop_hinge(replayer.model, name)
    states = replayer.feedback_states(props=True)
    if states is not None:
        path = states[2][:, at - replayer.nq]
    else:
        nstep = int(round(traj.duration / replayer.dt))
        init = replayer.initial_state(0)[None]
        rolled, _ = mujoco.rollout.rollout(replayer.model, replayer.data, init, replayer.controls(0, nstep)[None])
        path = rolled[0, :, 1 + at]
    per = int(round(FRAME_DT / replayer.dt))  # the state after physics step i is at time (i + 1) dt
    return np.r_[replayer.model.qpos0[at], path[per - 1 :: per]]


def body_contacts(robot, traj: Trajectory, name: str, every: int = 10) -> int:
    """How many of every `every`-th frame of the reference have the robot's body (any geom but those
    of the hands' bodies) touching the door panel at the record's door angle (MuJoCo's collision)."""
    from opt2skill.scene.build import build_model, prop_hinge

    model = build_model(robot, traj.scene)
    data = mujoco.MjData(model)
    door, at = traj.scene.prop(name), prop_hinge(model, name)
    panel = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
    hand_bodies = {int(model.site_bodyid[robot.site_id(robot.config.end_effectors[h])]) for h in HANDS}
    angle = door.angle_of(traj.prop_poses[name])
    count = 0
    for k in range(0, traj.num_frames, every):
        data.qpos[: robot.nq], data.qpos[at] = traj.qpos[k], angle[k]
        mujoco.mj_fwdPosition(model, data)
        for c in data.contact[: data.ncon]:
            pair = {int(c.geom1), int(c.geom2)}
            if panel in pair and c.dist < 0:
                other = (pair - {panel}).pop()
                if int(model.geom_bodyid[other]) not in hand_bodies and int(model.geom_bodyid[other]) != 0:
                    count += 1
                    break
    return count


def door_metrics(reference: Trajectory, tracked: Trajectory) -> dict[str, tuple[float, str]]:
    """The door's hinge angle in the tracked motion against the reference's: the final and the
    largest error (deg), until a fall; empty when the tracked record has no door state."""
    if DOOR not in tracked.prop_poses or DOOR not in reference.prop_poses:
        return {}
    door = reference.scene.prop(DOOR)
    ref = door.angle_of(reference.prop_poses[DOOR])
    got = door.angle_of(tracked.prop_poses[DOOR])
    n = min(len(got), len(ref))
    error = np.degrees(np.abs(got[:n] - ref[:n]))
    return {"door_angle_error": (float(error.max()), "deg"), "door_final_error": (float(error[-1]), "deg")}


INFO = TaskInfo(
    name="door_push",
    summary="push a spring-closed hinged door open with both hands while walking through the doorway",
    task=DoorPushTask,
    params=PARAMS,
    demo_ranges={"door_mass": (5.0, 10.0), "stiffness": (3.0, 6.0)},
    metrics=door_metrics,
)
