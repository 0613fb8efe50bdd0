"""Box pickup, shelf to shelf (paper Sec. IV-E): take a box from one board of a shelf, put it on another.

The scene: a shelf in front of the robot with two boards (`low`, `high`), the box on one of them,
its centre `reach` m ahead of the stand pose's base. The feet stay on their stand footholds. The
paper's five phases, as the plan's phases:

1. squat and reach: the hands go to pre-grasp points beside the box's side faces;
2. close and squeeze: the hands move onto the faces, then press on them as point contacts whose
   friction cones open along the faces' outward normals (the shelf still carries the box);
3. lift, retract slightly and stand: the box is a payload, half its mass at each hand;
4. carry it out past the board's front edge, to the other board's height, in over that board,
   lower it, squeeze there (point contacts again) and release;
5. return to the stand posture.

While the box is held, the record's hand forces are the box's dynamics plus a squeeze that lets
friction hold it (`skills.manipulation.held_object_forces`), so feet and hands together balance the
robot's and the box's momentum; the squeeze grows with the box's mass and its torques are in the
solve (`Phase.squeeze`), so the torque limits bind on them. In MuJoCo the box is a free body held by
friction alone.

Checks: the hands' friction cones at the box, and the optimizer's feedback expert in MuJoCo with the
real shelf and box must put the box within 3 cm of its target (`placement_error`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from opt2skill.data.record import Trajectory
from opt2skill.errors import ConfigError
from opt2skill.scene.description import Scene
from opt2skill.scene.props import Box, Shelf
from opt2skill.tasks import TaskInfo
from opt2skill.trajopt.config import require
from opt2skill.trajopt.frames import Frames
from opt2skill.trajopt.params import Param
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

PARAMS = (
    Param("low", allowed=(0.3, 0.95), default_range=(0.84, 0.90), unit="m", help="lower board's top"),
    Param("high", allowed=(0.8, 1.45), default_range=(1.20, 1.30), unit="m", help="upper board's top"),
    Param("upward", allowed=(0.0, 1.0), default_range=(0.0, 1.0), unit="", help="from 0.5: low to high; below: high to low"),
    Param("reach", allowed=(0.35, 0.6), default_range=(0.49, 0.53), unit="m", help="box centre ahead of the base"),
    Param("box_width", allowed=(0.2, 0.4), default_range=(0.27, 0.32), unit="m", help="box extent between the hands"),
    Param("box_mass", allowed=(0.0, 5.0), default_range=(0.3, 1.0), unit="kg", help="box mass"),
)


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
class BoxThresholds:
    hand_friction: float = 1.0  # N, largest hand force outside the hand-box friction cone
    placement_error: float = 0.03  # m, the box's final centre from its target, expert in MuJoCo
    placement_tilt: float = 10.0  # deg, the box's final turn from upright at its yaw, expert in MuJoCo

    def check(self) -> None:
        require(self.hand_friction > 0 and self.placement_error > 0 and self.placement_tilt > 0,
                "box thresholds must be > 0")


@dataclass(frozen=True)
class BoxPickupConfig(TaskConfig):
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
    thresholds: BoxThresholds = field(default_factory=BoxThresholds)
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
        for section in (self.timing, self.weights, self.thresholds, self.receding):
            section.check()


class BoxPickupTask(PhaseTask):
    name = "box_pickup"
    config_class = BoxPickupConfig
    params = PARAMS

    # -- the scene -------------------------------------------------------------------------------

    def boards(self, params: dict[str, float]) -> tuple[float, float]:
        """(source, target) board heights; a ConfigError when the box would not fit under the upper."""
        low, high = params["low"], params["high"]
        if high - low < self.config.box_height + self.config.board_gap:
            raise ConfigError(f"boards low = {low:g} m and high = {high:g} m are too close: the box "
                              f"({self.config.box_height:g} m) and the hands need "
                              f"{self.config.box_height + self.config.board_gap:g} m between them")
        return (low, high) if params["upward"] >= 0.5 else (high, low)

    def scene(self, params: dict[str, float]) -> Scene:
        cfg = self.config
        source, _ = self.boards(params)
        x = self.robot.stand_q_pin[0] + params["reach"]
        shelf_x = self.front_edge(params) + cfg.shelf_depth / 2
        shelf = Shelf(pos=(shelf_x, 0.0), width=max(0.8, params["box_width"] + 0.5), depth=cfg.shelf_depth,
                      boards=tuple(sorted((params["low"], params["high"]))))
        box = Box(size=(cfg.box_depth, params["box_width"], cfg.box_height), mass=max(params["box_mass"], 0.01),
                  pos=(x, 0.0, source + cfg.box_height / 2))
        return Scene(props=(shelf, box))

    def front_edge(self, params: dict[str, float]) -> float:
        """x of the shelf's front edge: the box stands 2 cm behind it."""
        return self.robot.stand_q_pin[0] + params["reach"] - self.config.box_depth / 2 - 0.02

    def box_centres(self, params: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        source, target = self.boards(params)
        x = self.robot.stand_q_pin[0] + params["reach"]
        h = self.config.box_height / 2
        return np.array([x, 0.0, source + h]), np.array([x, 0.0, target + h])

    def hand_offsets(self, params: dict[str, float]) -> dict[str, np.ndarray]:
        """From the box centre to each hand site at a grasp: half the width plus the hand's radius
        sideways, `grasp_height` up."""
        half = params["box_width"] / 2 + contact_radius(self.robot, "left_hand")
        up = self.config.grasp_height
        return {"left_hand": np.array([0.0, half, up]), "right_hand": np.array([0.0, -half, up])}

    # -- the plan --------------------------------------------------------------------------------

    def plan(self, params: dict[str, float]) -> Plan:
        cfg, w, T = self.config, self.config.weights, self.config.timing
        q0 = self.robot.stand_q_pin
        x0 = np.concatenate([q0, np.zeros(self.robot.nv)])
        feet = tuple(foot_contact(f) for f in stand_footholds(self.robot, q0).values())
        centre = np.mean([c.placement.translation for c in feet], axis=0)
        source, target = self.box_centres(params)
        offset = self.hand_offsets(params)
        normals = {h: offset[h] * [1, 1, 0] / np.linalg.norm(offset[h][:2]) for h in HANDS}  # the faces' normals
        home = end_effector_positions(self.robot, q0, HANDS)
        grasp = {h: source + offset[h] for h in HANDS}
        place = {h: target + offset[h] for h in HANDS}
        wide = {h: grasp[h] + cfg.pregrasp * normals[h] for h in HANDS}
        wide_at_target = {h: place[h] + cfg.pregrasp * normals[h] for h in HANDS}
        up = np.array([-cfg.retract, 0.0, cfg.lift])
        lifted = {h: grasp[h] + up for h in HANDS}
        # Around the boards: out past the shelf's front edge, to the other board's height, in above it.
        clear = self.front_edge(params) - cfg.box_depth / 2 - cfg.edge_clearance - source[0]
        out_here = {h: grasp[h] + np.array([clear, 0.0, cfg.lift]) for h in HANDS}
        out_there = {h: place[h] + np.array([clear, 0.0, cfg.carry_clearance]) for h in HANDS}
        above = {h: place[h] + np.array([0.0, 0.0, cfg.carry_clearance]) for h in HANDS}
        clear_of_board = {h: wide_at_target[h] + np.array([clear, 0.0, 0.0]) for h in HANDS}
        approach = {h: wide[h] + np.array([clear, 0.0, 0.0]) for h in HANDS}  # in front of the board edge
        held = tuple((h, params["box_mass"] / 2) for h in HANDS) if params["box_mass"] > 0 else ()
        squeeze = self.squeeze_force(params["box_mass"])

        def balance(knot: Knot, terms) -> list:
            out = [("com", terms.com([centre[0], centre[1], 0.0], (1, 1, 0)), w.com),
                   ("base_orientation", terms.rotation(self.robot.config.imu_site, np.eye(3)), w.base_orientation)]
            if knot.kind == "running" and w.acceleration > 0:
                out.append(("acceleration", terms.acceleration(1.0), w.acceleration))
            return out

        def hands_along(path: HandPath, weight: float):
            def costs(knot: Knot, terms) -> list:
                out = balance(knot, terms)
                if knot.kind == "impulse":
                    return []
                for h, p in path.at(knot.time).items():
                    out.append((f"{h}_path", terms.translation(self.robot.config.end_effectors[h], p), weight))
                return out

            return costs

        def touching(points: dict[str, np.ndarray]):
            def costs(knot: Knot, terms) -> list:
                if knot.kind == "running":
                    # A pure squeeze: opposite forces along the faces' normals, so the hands add no net
                    # force to the box and it rests on its board (the optimizer sees no box).
                    out = balance(knot, terms) + [
                        (f"{h}_squeeze", terms.contact_force(self.builder.frame_id(h), squeeze * normals[h], (1, 1, 1)),
                         w.squeeze) for h in points]
                    if knot.phase_time == 0.0:
                        # Hands that put the box down become contacts without an impact: they must
                        # arrive where the contact is and at rest, or the contact's constraint pulls
                        # them there, through the box, while the box already sits on the board.
                        ee = self.robot.config.end_effectors
                        out += [(f"{h}_arrive", terms.translation(ee[h], p), w.touch) for h, p in points.items()]
                        out += [(f"{h}_still", terms.velocity(ee[h], np.zeros(6), (1, 1, 1, 0, 0, 0)), w.touch)
                                for h in points]
                    return out
                if knot.kind != "impulse":
                    return balance(knot, terms)
                # the hands touch the faces where the grasp is planned (as walking's touchdown cost)
                return [(f"{h}_touch", terms.translation(self.robot.config.end_effectors[h], p), w.touch)
                        for h, p in points.items()]

            return costs

        phases: list[Phase] = []
        t = 0.0

        def add(duration: float, label: str, start, end, *, weight=w.hands, grasping=None, holding=False):
            nonlocal t
            contacts = feet + (grasp_contacts(grasping, normals) if grasping else ())
            path = HandPath(start, end, t, duration)
            costs = touching(grasping) if grasping else hands_along(path, weight)
            phases.append(Phase(duration, contacts, costs, label, payload=held if holding else (),
                                squeeze=squeeze if holding and held else 0.0))
            t += duration

        add(T.stand, "stand", home, home)
        add(T.reach, "squat and reach", home, approach)
        add(T.reach_in, "reach in", approach, wide)
        add(T.close, "close", wide, grasp, weight=w.held)
        add(T.squeeze, "squeeze", grasp, grasp, grasping=grasp)
        add(T.lift, "lift", grasp, lifted, weight=w.held, holding=True)
        add(T.out, "out of the board", lifted, out_here, weight=w.held, holding=True)
        add(T.carry, "to the other board", out_here, out_there, weight=w.held, holding=True)
        add(T.into, "over the board", out_there, above, weight=w.held, holding=True)
        add(T.lower, "lower", above, place, weight=w.held, holding=True)
        add(T.release, "release", place, place, grasping=place)
        add(T.open, "open", place, wide_at_target)
        add(T.withdraw, "withdraw", wide_at_target, clear_of_board)
        add(T.back, "return", clear_of_board, home)
        add(T.rest, "stand", home, home)
        return Plan(phases=phases, x0=x0, scene=self.scene(params), context=params)

    def squeeze_force(self, mass: float) -> float:
        """N each hand presses on a box of `mass` kg, on a board and while carrying it: the same on
        both, so nothing jumps when the box leaves a board."""
        cfg = self.config
        mu = self.robot.config.friction_coefficient * cfg.contact.friction_scale
        return max(cfg.squeeze, hold_squeeze(mass, mu, cfg.hold_margin, cfg.hold_acceleration))

    def optimize(self, problem: Problem, plan: Plan) -> Solution:
        rc = self.config.receding
        if not rc.enabled:
            return super().optimize(problem, plan)
        return solve_standing(problem, self.config.solver, rc)

    def complete_frames(self, plan: Plan, problem: Problem, frames: Frames, knots: dict) -> Frames:
        params = plan.context
        frames.prop_poses = {"box": _box_poses(self.robot, plan.scene.prop("box"), self.box_centres(params)[1],
                                               problem, frames)}
        if params["box_mass"] > 0:
            held_object_forces(self.robot, problem, frames, knots, HANDS)
        return frames

    # -- checks ----------------------------------------------------------------------------------

    def task_errors(self, traj: Trajectory) -> dict[str, dict[str, Any]]:
        th = self.config.thresholds
        _, target = self.box_centres(traj.params)
        position, quat = expert_box_pose(self.robot, traj, "box")
        mu = self.robot.config.friction_coefficient
        # The box stands upright at its yaw (0) on the target: a box tipped onto a side can end
        # with its centre close to the target too.
        tilt = float(np.degrees(2 * np.arccos(min(1.0, abs(quat[0])))))
        return {
            "hand_friction": {"value": hand_friction_violation(traj, mu), "limit": th.hand_friction, "unit": "N"},
            "placement_error": {"value": float(np.linalg.norm(position - target)), "limit": th.placement_error, "unit": "m"},
            "placement_tilt": {"value": tilt, "limit": th.placement_tilt, "unit": "deg"},
        }


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


def expert_box_pose(robot, traj: Trajectory, box: str) -> tuple[np.ndarray, np.ndarray]:
    """Where the box ends (centre, quaternion w x y z) when the optimizer's feedback expert plays the
    record in MuJoCo with the real props (the shelf, the box as a free body held by friction); a
    record without the solver's gains is played open loop (reference torques and PD) instead."""
    from opt2skill.data.replay import Replayer

    replayer = Replayer(robot, traj)
    if replayer.feedback() is None:
        replayer.full()
    body = mujoco.mj_name2id(replayer.model, mujoco.mjtObj.mjOBJ_BODY, box)
    return replayer.data.xpos[body].copy(), replayer.data.xquat[body].copy()


def _box_poses(robot, box: Box, target: np.ndarray, problem: Problem, frames: Frames) -> np.ndarray:
    """The box's reference poses (T, 7): on its board until both hands touch it, then with the hands
    until they let go, then on the target board at `target` (its centre)."""
    hands = [list(problem.contact_names).index(h) for h in HANDS]
    (geom,) = box.geoms()
    return held_object_poses(robot, frames.q, frames.active[:, hands].all(axis=1), HANDS,
                             np.r_[geom.centre, geom.quat], put=np.r_[target, geom.quat])


INFO = TaskInfo(
    name="box_pickup",
    summary="pick a box up from one shelf board and place it on another (paper Sec. IV-E)",
    task=BoxPickupTask,
    params=PARAMS,
    demo_ranges={"box_mass": (0.3, 0.6), "upward": (0.6, 1.0)},
)
