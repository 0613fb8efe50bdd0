"""A box taken from a shelf board, carried and put on a board with both hands (paper Sec. IV-E).

The skill the box tasks share (`tasks.box_pickup`, `tasks.box_heavy`, `tasks.box_walk`): the scene
(a shelf in front of the robot, the box a free body on one of its boards, `reach` m ahead of the
stand pose's base), the config fields of a box at a shelf (`BoxHandlingConfig`), and the phases,
built by `BoxPhases` one after the other on one clock:

- `take`: stand; squat and reach to a point in front of the board's edge; reach in beside the box;
  close onto its side faces; squeeze (the hands are point contacts whose friction cones open along
  the faces' outward normals, their forces pulled to a pure squeeze, the board still carries the
  box); lift and retract slightly (the box is a payload, half its mass at each hand, squeezed inside
  the solve: `trajopt.squeeze`); out past the board's front edge. The feet stay on their stand
  footholds.
- `put`: to another board's height, in over it, lower, squeeze and release, open, withdraw in front
  of the board, return to the stand posture.

A task that walks with the box after `take` (`tasks.box_walk`) adds its own phases with `carried`.
While the box is held, the record's hand forces are the box's dynamics plus the squeeze
(`skills.manipulation.held_object_forces`), so feet and hands together balance the robot's and the
box's momentum. In MuJoCo the box is a free body held by friction alone.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import mujoco
import numpy as np

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.scene.description import Scene
from opt2skill.scene.props import Box, Shelf
from opt2skill.trajopt.config import require
from opt2skill.trajopt.frames import Frames
from opt2skill.trajopt.phase_task import PhaseTask, Plan
from opt2skill.trajopt.phases import Knot, Phase, Problem
from opt2skill.trajopt.posture import Posture
from opt2skill.trajopt.receding import solve_standing
from opt2skill.trajopt.settings import ContactSettings, SolverSettings
from opt2skill.trajopt.skills.locomotion import foot_contact, stand_footholds
from opt2skill.trajopt.skills.manipulation import (HandPath, contact_radius, end_effector_positions, grasp_contacts,
                                                   held_object_forces, held_object_poses, hold_squeeze)
from opt2skill.trajopt.skills.stride_guess import RecedingSettings
from opt2skill.trajopt.solver import Solution
from opt2skill.trajopt.task_config import TaskConfig

HANDS = ("left_hand", "right_hand")


@dataclass(frozen=True)
class Timing:
    """Seconds of each phase (multiples of the 5-ms frame)."""

    stand: float = 0.3
    reach: float = 1.0
    reach_in: float = 0.6
    close: float = 0.5
    squeeze: float = 0.4
    lift: float = 0.5
    out: float = 0.8
    carry: float = 1.4
    into: float = 0.8
    lower: float = 0.5
    release: float = 0.4
    open: float = 0.5
    withdraw: float = 0.6
    back: float = 1.2
    rest: float = 0.4

    def check(self) -> None:
        require(all(0.005 <= v <= 5.0 for v in vars(self).values()), "timing: every phase must last 0.005 to 5 s")


@dataclass(frozen=True)
class BoxWeights:
    hands: float = 1e4  # hand positions along their paths
    held: float = 1e5  # hand positions while the box is held (keeps the box rigid between them)
    touch: float = 1e6  # hand positions where they touch the box
    squeeze: float = 1e3  # hand forces towards a pure squeeze while the box rests on a board
    com: float = 1e3  # CoM over the middle of the feet
    base_orientation: float = 3e3  # upright: a leaning torso meets the box or the board above
    # On the generalized accelerations at every running node: the plan chattered between knots
    # (hands at up to 47 m/s^2 in single frames, which the box's forces on the hands follow, and
    # joint speeds past their limits in the reach-in); 1.0 made the feedback expert fall.
    acceleration: float = 0.1

    def check(self) -> None:
        require(all(v >= 0 for v in vars(self).values()), "box weights must be >= 0")


@dataclass(frozen=True)
class BoxHandlingConfig(TaskConfig):
    """The config fields of every task that handles a box at a shelf with this skill."""

    box_depth: float = 0.16  # m, along x
    box_height: float = 0.2  # m
    shelf_depth: float = 0.4  # m
    pregrasp: float = 0.08  # m beside a face before closing on it
    retract: float = 0.05  # m the box is pulled back (towards the robot) when lifted
    lift: float = 0.04  # m the box is lifted off a board
    # m above the target board the box is carried in over it. In MuJoCo a held box creeps down
    # between the hands (soft friction: about 1 cm/s under its weight, whatever the squeeze), so
    # by then it hangs 3 to 4 cm lower than planned and scraped the board's edge at `lift`.
    carry_clearance: float = 0.08
    board_gap: float = 0.1  # m of free height above the box on the lower board, at least
    edge_clearance: float = 0.04  # m between the box and a board's front edge when it passes the board
    squeeze: float = 20.0  # N each hand presses on the box at least (on a board and while carrying it)
    # While carrying, each hand presses at least enough for friction (the optimizer's cone) to hold
    # half the box with `hold_margin` while the box accelerates by `hold_acceleration` (m/s^2); the
    # arms' torques hold that squeeze inside the solve (`skills.manipulation.hold_squeeze`).
    hold_margin: float = 1.5
    hold_acceleration: float = 6.0
    # m above the box's centre where the hands press. Two point contacts hold the box's position
    # but not its turn about the line between them: pressed above its centre the box hangs below
    # that line like a pendulum and rights itself; pressed at the centre any knock tilts it for good.
    grasp_height: float = 0.04
    timing: Timing = field(default_factory=Timing)
    weights: BoxWeights = field(default_factory=BoxWeights)
    receding: RecedingSettings = field(default_factory=lambda: RecedingSettings(retry_window=0.0))
    # Legs ten times stiffer than walking's: with the boards' heights no squat is needed, and a
    # soft posture let the optimizer dip and bounce the base to help the hands along.
    posture: Posture = field(default_factory=lambda: Posture(legs=30.0, leg_velocity=3.0, base_velocity=10.0))
    # The hands' touchdown impulses without the feet (the builder's old rule): with the feet held in
    # them the test record's plan was cheaper (cost 16.4k against 31.3k) but the box, swinging
    # below the hands, was put down on its side in MuJoCo (tilt 90 degrees against 0.16); not re-tuned.
    contact: ContactSettings = field(default_factory=lambda: ContactSettings(min_normal_force=10.0, impacts_hold=False))
    solver: SolverSettings = field(default_factory=lambda: SolverSettings(dt=0.02, max_iter=200, reg_init=1e-4))

    def check_own(self) -> None:
        require(0.1 <= self.box_depth <= 0.4 and 0.1 <= self.box_height <= 0.4, "box_depth and box_height must be in [0.1, 0.4] m")
        require(0.02 <= self.pregrasp <= 0.2, "pregrasp must be in [0.02, 0.2] m")
        require(0.0 <= self.squeeze <= 200.0, "squeeze must be in [0, 200] N")
        require(1.0 <= self.hold_margin <= 5.0 and 0.0 <= self.hold_acceleration <= 20.0,
                "hold_margin must be in [1, 5], hold_acceleration in [0, 20] m/s^2")
        require(0.0 <= self.grasp_height <= self.box_height / 2 - 0.02,
                f"grasp_height must be in [0, {self.box_height / 2 - 0.02:g}] m (below the box's top edge)")
        require(0.0 <= self.retract <= 0.15 and 0.01 <= self.lift <= 0.1 and 0.01 <= self.carry_clearance <= 0.1,
                "retract in [0, 0.15] m, lift and carry_clearance in [0.01, 0.1] m")
        for section in (self.timing, self.weights, self.receding):
            section.check()


class BoxHandlingTask(PhaseTask):
    """A task with a box on a shelf board in front of the robot. Its params have `reach`,
    `box_width` and `box_mass`; the task says which boards the shelf has and where the box starts
    (`shelf_boards`, `source_board`), and where it is put down (`put_target`, None: never)."""

    config: BoxHandlingConfig

    def shelf_boards(self, params: dict[str, float]) -> tuple[float, ...]:
        raise NotImplementedError

    def source_board(self, params: dict[str, float]) -> float:
        raise NotImplementedError

    def put_target(self, params: dict[str, float]) -> np.ndarray | None:
        """Where the box's centre rests after the motion, if it is put down."""
        return None

    # -- the scene -------------------------------------------------------------------------------

    def scene(self, params: dict[str, float]) -> Scene:
        cfg = self.config
        shelf_x = self.front_edge(params) + cfg.shelf_depth / 2
        shelf = Shelf(pos=(shelf_x, 0.0), width=max(0.8, params["box_width"] + 0.5), depth=cfg.shelf_depth,
                      boards=tuple(sorted(self.shelf_boards(params))))
        box = Box(size=(cfg.box_depth, params["box_width"], cfg.box_height), mass=max(params["box_mass"], 0.01),
                  pos=tuple(self.box_centre(params, self.source_board(params))))
        return Scene(props=(shelf, box))

    def front_edge(self, params: dict[str, float]) -> float:
        """x of the shelf's front edge: the box stands 2 cm behind it."""
        return self.robot.stand_q_pin[0] + params["reach"] - self.config.box_depth / 2 - 0.02

    def box_centre(self, params: dict[str, float], board: float) -> np.ndarray:
        """The box's centre standing on a board `board` m high."""
        return np.array([self.robot.stand_q_pin[0] + params["reach"], 0.0, board + self.config.box_height / 2])

    def hand_offsets(self, params: dict[str, float]) -> dict[str, np.ndarray]:
        """From the box centre to each hand site at a grasp: half the width plus the hand's radius
        sideways, `grasp_height` up."""
        half = params["box_width"] / 2 + contact_radius(self.robot, "left_hand")
        up = self.config.grasp_height
        return {"left_hand": np.array([0.0, half, up]), "right_hand": np.array([0.0, -half, up])}

    def squeeze_force(self, mass: float) -> float:
        """N each hand presses on a box of `mass` kg, on a board and while carrying it: the same on
        both, so nothing jumps when the box leaves a board."""
        cfg = self.config
        mu = self.robot.config.friction_coefficient * cfg.contact.friction_scale
        return max(cfg.squeeze, hold_squeeze(mass, mu, cfg.hold_margin, cfg.hold_acceleration))

    def box_phases(self, params: dict[str, float]) -> BoxPhases:
        return BoxPhases(self, params)

    # -- solve and record ------------------------------------------------------------------------

    def optimize(self, problem: Problem, plan: Plan) -> Solution:
        rc = self.config.receding
        if not rc.enabled:
            return super().optimize(problem, plan)
        return solve_standing(problem, self.config.solver, rc)

    def complete_frames(self, plan: Plan, problem: Problem, frames: Frames, knots: dict) -> Frames:
        params = plan.context
        if params["box_mass"] > 0:
            held_object_forces(self.robot, problem, frames, knots, HANDS)
        # after the carrying phases' hands became active: the box moves with them
        frames.prop_poses = {"box": _box_poses(self.robot, plan.scene.prop("box"), self.put_target(params),
                                               problem, frames)}
        return frames


class BoxPhases:
    """The phases of handling one box, appended one after the other (`phases`, ending at `t`)."""

    def __init__(self, task: BoxHandlingTask, params: dict[str, float]):
        self.task, self.robot, self.params = task, task.robot, params
        cfg = task.config
        self.weights = cfg.weights
        q0 = self.robot.stand_q_pin
        self.feet = tuple(foot_contact(f) for f in stand_footholds(self.robot, q0).values())
        self.centre = np.mean([c.placement.translation for c in self.feet], axis=0)
        self.offset = task.hand_offsets(params)
        self.normals = {h: self.offset[h] * [1, 1, 0] / np.linalg.norm(self.offset[h][:2]) for h in HANDS}  # the faces' normals
        self.home = end_effector_positions(self.robot, q0, HANDS)
        self.held = tuple((h, params["box_mass"] / 2) for h in HANDS) if params["box_mass"] > 0 else ()
        self.squeeze = task.squeeze_force(params["box_mass"])
        self.phases: list[Phase] = []
        self.t = 0.0

    # -- costs -----------------------------------------------------------------------------------

    def balance(self, knot: Knot, terms) -> list:
        """Standing on the stand footholds: CoM over the middle of the feet, torso upright, smooth."""
        w = self.weights
        out = [("com", terms.com([self.centre[0], self.centre[1], 0.0], (1, 1, 0)), w.com),
               ("base_orientation", terms.rotation(self.robot.config.imu_site, np.eye(3)), w.base_orientation)]
        return out + self.smooth(knot, terms)

    def smooth(self, knot: Knot, terms) -> list:
        """The acceleration cost of every running node (the plan chatters without it)."""
        w = self.weights
        if knot.kind == "running" and w.acceleration > 0:
            return [("acceleration", terms.acceleration(1.0), w.acceleration)]
        return []

    def hand_terms(self, targets, weight: float):
        """Costs of the hands following `targets` (t -> {hand: position}); none at impulse nodes."""
        ee = self.robot.config.end_effectors

        def costs(knot: Knot, terms) -> list:
            if knot.kind == "impulse":
                return []
            return [(f"{h}_path", terms.translation(ee[h], p), weight) for h, p in targets(knot.time).items()]

        return costs

    def standing(self, targets, weight: float):
        """Balance on the stand footholds with the hands following `targets`; none at impulse nodes."""
        hands = self.hand_terms(targets, weight)

        def costs(knot: Knot, terms) -> list:
            return [] if knot.kind == "impulse" else self.balance(knot, terms) + hands(knot, terms)

        return costs

    def touching(self, points: dict[str, np.ndarray]):
        w, ee = self.weights, self.robot.config.end_effectors
        builder = self.task.builder

        def costs(knot: Knot, terms) -> list:
            if knot.kind == "running":
                # A pure squeeze: opposite forces along the faces' normals, so the hands add no net
                # force to the box and it rests on its board (the optimizer sees no box).
                out = self.balance(knot, terms) + [
                    (f"{h}_squeeze", terms.contact_force(builder.frame_id(h), self.squeeze * self.normals[h], (1, 1, 1)),
                     w.squeeze) for h in points]
                if knot.phase_time == 0.0:
                    # Hands that put the box down become contacts without an impact: they must
                    # arrive where the contact is and at rest, or the contact's constraint pulls
                    # them there, through the box, while the box already sits on the board.
                    out += [(f"{h}_arrive", terms.translation(ee[h], p), w.touch) for h, p in points.items()]
                    out += [(f"{h}_still", terms.velocity(ee[h], np.zeros(6), (1, 1, 1, 0, 0, 0)), w.touch)
                            for h in points]
                return out
            if knot.kind != "impulse":
                return self.balance(knot, terms)
            # the hands touch the faces where the grasp is planned (as walking's touchdown cost)
            return [(f"{h}_touch", terms.translation(ee[h], p), w.touch) for h, p in points.items()]

        return costs

    # -- phases ----------------------------------------------------------------------------------

    def add(self, duration: float, label: str, start, end, *, weight=None, grasping=None, holding=False) -> None:
        """A phase on the stand footholds: the hands along a path from `start` to `end`, or on the
        box's faces at `grasping` (point contacts); `holding`: carrying the box."""
        weight = self.weights.hands if weight is None else weight
        contacts = self.feet + (grasp_contacts(grasping, self.normals) if grasping else ())
        path = HandPath(start, end, self.t, duration)
        costs = self.touching(grasping) if grasping else self.standing(path.at, weight)
        self.phases.append(Phase(duration, contacts, costs, label, payload=self.held if holding else (),
                                 squeeze=self.squeeze if holding and self.held else 0.0))
        self.t += duration

    def carry(self, phase: Phase, targets) -> None:
        """Append `phase` (another skill's: a step of a walk) with the box held between the hands:
        the payload and its squeeze, and on top of the phase's own costs the hands following
        `targets` (t -> {hand: position}) and the acceleration cost."""
        hands = self.hand_terms(targets, self.weights.held)

        def costs(knot: Knot, terms) -> list:
            return list(phase.costs(knot, terms)) + hands(knot, terms) + self.smooth(knot, terms)

        self.phases.append(dataclasses.replace(phase, costs=costs, payload=self.held,
                                               squeeze=self.squeeze if self.held else 0.0))
        self.t += phase.duration

    def take(self, board: float) -> dict[str, np.ndarray]:
        """Stand, reach, grasp the box on board `board`, lift it and carry it out past the board's
        front edge; returns the hands' positions there."""
        cfg, T, w = self.task.config, self.task.config.timing, self.weights
        source = self.task.box_centre(self.params, board)
        grasp = {h: source + self.offset[h] for h in HANDS}
        wide = {h: grasp[h] + cfg.pregrasp * self.normals[h] for h in HANDS}
        lifted = {h: grasp[h] + np.array([-cfg.retract, 0.0, cfg.lift]) for h in HANDS}
        self.clear = self.task.front_edge(self.params) - cfg.box_depth / 2 - cfg.edge_clearance - source[0]
        out_here = {h: grasp[h] + np.array([self.clear, 0.0, cfg.lift]) for h in HANDS}
        approach = {h: wide[h] + np.array([self.clear, 0.0, 0.0]) for h in HANDS}  # in front of the board edge
        self.add(T.stand, "stand", self.home, self.home)
        self.add(T.reach, "squat and reach", self.home, approach)
        self.add(T.reach_in, "reach in", approach, wide)
        self.add(T.close, "close", wide, grasp, weight=w.held)
        self.add(T.squeeze, "squeeze", grasp, grasp, grasping=grasp)
        self.add(T.lift, "lift", grasp, lifted, weight=w.held, holding=True)
        self.add(T.out, "out of the board", lifted, out_here, weight=w.held, holding=True)
        return out_here

    def put(self, held_at: dict[str, np.ndarray], board: float) -> None:
        """From the hands at `held_at` in front of the shelf: to board `board`'s height, in over it,
        lower the box onto it, release, withdraw and return to the stand posture."""
        cfg, T, w = self.task.config, self.task.config.timing, self.weights
        target = self.task.box_centre(self.params, board)
        place = {h: target + self.offset[h] for h in HANDS}
        wide_at_target = {h: place[h] + cfg.pregrasp * self.normals[h] for h in HANDS}
        out_there = {h: place[h] + np.array([self.clear, 0.0, cfg.carry_clearance]) for h in HANDS}
        above = {h: place[h] + np.array([0.0, 0.0, cfg.carry_clearance]) for h in HANDS}
        clear_of_board = {h: wide_at_target[h] + np.array([self.clear, 0.0, 0.0]) for h in HANDS}
        self.add(T.carry, "to the other board", held_at, out_there, weight=w.held, holding=True)
        self.add(T.into, "over the board", out_there, above, weight=w.held, holding=True)
        self.add(T.lower, "lower", above, place, weight=w.held, holding=True)
        self.add(T.release, "release", place, place, grasping=place)
        self.add(T.open, "open", place, wide_at_target)
        self.add(T.withdraw, "withdraw", wide_at_target, clear_of_board)
        self.add(T.back, "return", clear_of_board, self.home)
        self.add(T.rest, "stand", self.home, self.home)


# -- checks ------------------------------------------------------------------------------------------


def hand_friction_violation(traj: Trajectory, mu: float) -> float:
    """Largest max(0, |f_t| - mu f_n, -f_n) (N) of the hands' forces, the normal of each hand being
    the line between the hands (outward), whenever a hand touches the box."""
    names = list(traj.contact_names)
    ee = list(traj.ee_names)
    left, right = (names.index(h) for h in HANDS)
    axis = traj.ee_pos[:, ee.index("left_hand")] - traj.ee_pos[:, ee.index("right_hand")]
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    worst = 0.0
    for c, n in ((left, axis), (right, -axis)):
        on = traj.contact_active[:, c]
        f = traj.contact_wrench[on, c, :3]
        fn = np.einsum("ij,ij->i", f, n[on])
        ft = np.linalg.norm(f - fn[:, None] * n[on], axis=1)
        worst = max(worst, float(np.max(np.maximum(ft - mu * fn, -fn), initial=0.0)))
    return worst


def expert_box_path(robot, traj: Trajectory, box: str) -> np.ndarray:
    """(F, 7) the box's pose (centre, quaternion w x y z) at each 200 Hz frame while the optimizer's
    feedback expert plays the record in MuJoCo with the real props (the shelf, the box as a free
    body held by friction), until the robot falls (F <= the record's frames); a record without the
    solver's gains is played open loop (reference torques and PD) instead."""
    from opt2skill.data.replay import Replayer
    from opt2skill.scene.build import prop_qpos

    replayer = Replayer(robot, traj)
    at = prop_qpos(replayer.model, box)
    states = replayer.feedback_states(props=True)
    if states is not None:
        path = states[2][:, at.start - replayer.nq : at.stop - replayer.nq]
    else:
        nstep = int(round(traj.duration / replayer.dt))
        init = replayer.initial_state(0)[None]
        rolled, _ = mujoco.rollout.rollout(replayer.model, replayer.data, init, replayer.controls(0, nstep)[None])
        path = rolled[0, :, 1 + at.start : 1 + at.stop]
    per = int(round(FRAME_DT / replayer.dt))  # the state after physics step i is at time (i + 1) dt
    return np.vstack([replayer.model.qpos0[at][None], path[per - 1 :: per]])


def expert_box_pose(robot, traj: Trajectory, box: str) -> tuple[np.ndarray, np.ndarray]:
    """Where the box ends (centre, quaternion w x y z) in `expert_box_path`'s replay."""
    end = expert_box_path(robot, traj, box)[-1]
    return end[:3].copy(), end[3:].copy()


def _box_poses(robot, box: Box, target: np.ndarray | None, problem: Problem, frames: Frames) -> np.ndarray:
    """The box's reference poses (T, 7): on its board until both hands touch it, then with the hands
    until they let go, then on the target board at `target` (its centre; None: where it was let go)."""
    hands = [list(problem.contact_names).index(h) for h in HANDS]
    held = frames.active[:, hands].all(axis=1)
    (geom,) = box.geoms()
    return held_object_poses(robot, frames.q, held, HANDS, np.r_[geom.centre, geom.quat],
                             put=None if target is None else np.r_[target, geom.quat])
