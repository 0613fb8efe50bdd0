"""Drawing and wiping with a prescribed contact force (paper Sec. IV-F and Table IV).

The robot stands at a desk (top at `desk_height`). The right hand draws two line segments on the
desk top, then the left hand wipes them with a stroke across and back, each hand following
subgoals on the surface (`HandPath`). While a hand is on the desk it is a 3D point contact sliding
along its stroke (`skills.manipulation.sliding_contact`), its friction cone along the desk's normal,
and it presses with the prescribed force profile: `force` N, ramped up and down over `force_ramp`
s at both ends of each contact (`force_profile`). The optimizer pulls the contact force towards
that normal force plus the desk's sliding friction (mu_desk times it, against the hand's motion),
so the reference's force is what a hand wiping the desk in MuJoCo meets: the desk's friction is
the contact's there (`scene.build`).

Checks: the reference's normal force against the profile (`force_error`, N), the hand forces in the
robot's friction cone (`hand_friction`, N), the hands on the desk top while in contact
(`hand_off_surface`, mm), and the force the optimizer's feedback expert presses with in MuJoCo with
the real desk (`expert_force_error`, N, mean over the frames the profile holds at least 1 N).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.tasks import TaskInfo
from opt2skill.trajopt.config import require
from opt2skill.trajopt.params import Param
from opt2skill.trajopt.phases import Knot, Phase
from opt2skill.trajopt.skills.gait import smoothstep
from opt2skill.trajopt.phase_task import Plan
from opt2skill.trajopt.skills.desk import DeskConfig, DeskTask, Stand, StandingCosts
from opt2skill.trajopt.skills.manipulation import HandPath, contact_radius, sliding_contact

SENSOR_WINDOW = 0.05  # s, a force sensor's averaging window (`sensor_mean`), the dataset's check's and Table IV's

HANDS = ("left_hand", "right_hand")
UP = np.array([0.0, 0.0, 1.0])

PARAMS = (
    Param("desk_height", allowed=(0.5, 1.5), default_range=(0.85, 0.95), unit="m", help="desk top above the floor"),
    Param("force", allowed=(0.0, 25.0), default_range=(0.0, 25.0), unit="N", help="normal force the hand presses with"),
    Param("reach", allowed=(0.38, 0.5), default_range=(0.40, 0.45), unit="m", help="strokes' centre ahead of the base"),
)


@dataclass(frozen=True)
class Timing:
    """Seconds of each phase (multiples of the 5-ms frame)."""

    stand: float = 0.3
    rise: float = 0.4  # hands up to the height they cross the desk's edge at, or down from it
    reach: float = 0.8  # a hand from where it is to above a stroke's start
    lower: float = 0.3  # down onto the desk
    stroke: float = 0.9  # along one segment, pressing
    lift: float = 0.3
    back: float = 0.8  # a hand back over the desk's edge
    rest: float = 0.4

    def check(self) -> None:
        require(all(0.005 <= v <= 5.0 for v in vars(self).values()), "timing: every phase must last 0.005 to 5 s")


@dataclass(frozen=True)
class WipeWeights:
    hands: float = 1e4  # hand positions along their paths (free hands)
    touch: float = 1e6  # a hand where it touches the desk (impulse nodes)
    force: float = 1e2  # contact force towards the profile's (N^-2)
    com: float = 1e3  # CoM over the middle of the feet
    base_orientation: float = 1e3
    feet: float = 1e-2  # each foot's wrench towards half the weight (skills.desk.StandingCosts)

    def check(self) -> None:
        require(all(v >= 0 for v in vars(self).values()), "wipe weights must be >= 0")


@dataclass(frozen=True)
class WipeThresholds:
    force_error: float = 2.0  # N, largest |reference normal force - profile| while in contact
    hand_friction: float = 1.0  # N, largest hand force outside the robot's friction cone
    hand_off_surface: float = 3.0  # mm, largest distance of a contact hand from the desk top
    expert_force_error: float = 2.5  # N, mean |MuJoCo normal force (50-ms means) - profile|, expert replay

    def check(self) -> None:
        require(all(v > 0 for v in vars(self).values()), "wipe thresholds must be > 0")


@dataclass(frozen=True)
class WipeConfig(DeskConfig):
    desk_gap: float = 0.26  # m: the strokes start 8 cm or more beyond the edge
    desk_friction: float = 0.3  # a whiteboard's: the hands slide with this friction
    line_length: float = 0.12  # m, each drawn segment (along x)
    lines_y: tuple[float, float] = (-0.10, -0.04)  # m, the two drawn segments' y
    wipe_y: tuple[float, float] = (0.02, -0.12)  # m, the wipe's ends (across the lines)
    wipe_spacing: float = 0.06  # m between the wipe's stroke across and its stroke back
    hover: float = 0.05  # m above the desk before touching it
    force_ramp: float = 0.25  # s, the force's ramp up and down at both ends of a contact
    expert_force_window: float = SENSOR_WINDOW  # s, the MuJoCo force's averaging window (`expert_normal_forces`)
    slip_speed: float = 0.02  # m/s, the sliding friction's regularization (tanh(|v| / this))
    timing: Timing = field(default_factory=Timing)
    weights: WipeWeights = field(default_factory=WipeWeights)
    thresholds: WipeThresholds = field(default_factory=WipeThresholds)

    def check_own(self) -> None:
        require(self.desk_friction <= 0.5, "desk_friction must be at most 0.5 (inside the optimizer's cone)")
        require(0.02 <= self.line_length <= 0.3, "line_length must be in [0.02, 0.3] m")
        require(0.0 < self.force_ramp <= self.timing.stroke / 2, "force_ramp must be in (0, timing.stroke / 2] s")
        require(0.005 <= self.expert_force_window <= 0.5, "expert_force_window must be in [0.005, 0.5] s")
        require(self.slip_speed > 0 and 0.01 <= self.hover <= 0.2, "slip_speed > 0, hover in [0.01, 0.2] m")
        super().check_own()
        for section in (self.timing, self.weights, self.thresholds):
            section.check()


@dataclass(frozen=True)
class Touch:
    """One hand on the desk over [start, end] (s): the force profile's support."""

    hand: str
    start: float
    end: float


def force_profile(t: np.ndarray | float, touches: list[Touch], hand: str, force: float, ramp: float) -> np.ndarray:
    """The prescribed normal force (N) of `hand` at times t: `force` ramped up over `ramp` s after
    each touchdown and down over `ramp` s before each lift-off (smoothsteps), 0 off the desk."""
    t = np.asarray(t, dtype=float)
    out = np.zeros_like(t)
    for c in touches:
        if c.hand == hand:
            inside = (t >= c.start - 1e-9) & (t <= c.end + 1e-9)
            envelope = smoothstep((t - c.start) / ramp) * smoothstep((c.end - t) / ramp)
            out = np.where(inside, force * envelope, out)
    return out


class WipeTask(DeskTask):
    name = "wipe"
    config_class = WipeConfig
    params = PARAMS
    doing = "draw and wipe"

    def on_desk(self, params: dict[str, float], x: float, y: float) -> np.ndarray:
        """The hand site's position with the hand resting on the desk top at (x, y) ahead of the base."""
        base = self.robot.stand_q_pin
        return np.array([base[0] + x, base[1] + y, params["desk_height"] + contact_radius(self.robot, "left_hand")])

    def strokes(self, params: dict[str, float]) -> list[tuple[str, list[np.ndarray]]]:
        """(hand, waypoints on the desk) of each contact: the two drawn lines, then the wipe."""
        cfg, r = self.config, params["reach"]
        half = cfg.line_length / 2
        lines = [("right_hand", [self.on_desk(params, r - half, y), self.on_desk(params, r + half, y)]) for y in cfg.lines_y]
        a, b = cfg.wipe_y
        s = cfg.wipe_spacing / 2
        wipe = ("left_hand", [self.on_desk(params, r - s, a), self.on_desk(params, r - s, b),
                              self.on_desk(params, r + s, b), self.on_desk(params, r + s, a)])
        return lines + [wipe]

    # -- the plan --------------------------------------------------------------------------------

    def plan(self, params: dict[str, float]) -> Plan:
        self.check_reach(params)
        cfg, w, T = self.config, self.config.weights, self.config.timing
        stand = Stand.of(self.robot)
        feet, home = stand.feet, {h: stand.home[h] for h in HANDS}
        standing = StandingCosts(self.robot, stand, w.com, w.base_orientation, w.hands, w.feet)
        where = dict(home)
        phases: list[Phase] = []
        touches: list[Touch] = []
        mu = cfg.desk_friction
        t = 0.0

        def free(path: HandPath):
            def costs(knot: Knot, terms) -> list:
                return [] if knot.kind == "impulse" else standing.balance(terms) + standing.along(terms, knot, path, HANDS)
            return costs

        def pressing(path: HandPath, hand: str, other: str, hold: np.ndarray):
            def costs(knot: Knot, terms) -> list:
                if knot.kind == "impulse":  # the hand touches the desk where its stroke starts
                    return [(f"{hand}_touch", terms.translation(self.robot.config.end_effectors[hand],
                                                                path.start[hand]), w.touch)]
                # the node's force holds over its step: aim at the profile's middle of the step
                middle = knot.time + (cfg.solver.dt / 2 if knot.kind == "running" else 0.0)
                fn = float(force_profile(middle, touches, hand, params["force"], cfg.force_ramp))
                _, v, _ = path.motion(hand, middle)
                speed = float(np.linalg.norm(v))
                along = v / speed if speed > 1e-9 else np.zeros(3)
                target = fn * UP - mu * fn * np.tanh(speed / cfg.slip_speed) * along  # the desk's force on the hand
                return standing.balance(terms) + [
                    (f"{hand}_force", terms.contact_force(self.builder.frame_id(hand), target, (1, 1, 1)), w.force),
                    (f"{other}_path", terms.translation(self.robot.config.end_effectors[other], hold), w.hands)]
            return costs

        def move(duration: float, label: str, targets: dict[str, np.ndarray]):
            nonlocal t
            path = HandPath(dict(where), {**where, **targets}, t, duration)
            phases.append(Phase(duration, feet, free(path), label))
            where.update(targets)
            t += duration

        # A hand crosses the desk's front edge only as high as it hovers over the desk: straight
        # from its home (in front of the edge, below the top) to a stroke it would hit the edge.
        height = params["desk_height"] + contact_radius(self.robot, "left_hand") + cfg.hover
        clear = {h: np.array([home[h][0], home[h][1], height]) for h in HANDS}
        over = set()
        move(T.stand, "stand", {})
        for hand, points in self.strokes(params):
            other = HANDS[1 - HANDS.index(hand)]
            if hand not in over or other in over:
                move(T.rise, "clear of the desk's edge", {h: clear[h] for h in (hand, other) if (h == hand) != (h in over)})
                over.discard(other)
            move(T.reach, f"{hand} above", {hand: points[0] + cfg.hover * UP, other: home[other]})
            over.add(hand)
            move(T.lower, f"{hand} down", {hand: points[0]})
            touches.append(Touch(hand, t, t + T.stroke * (len(points) - 1)))
            for a, b in zip(points[:-1], points[1:]):
                path = HandPath({hand: a}, {hand: b}, t, T.stroke)
                touch = (sliding_contact(hand, path, UP, min_normal_force=0.0),)
                phases.append(Phase(T.stroke, feet + touch, pressing(path, hand, other, where[other].copy()),
                                    f"{hand} stroke"))
                t += T.stroke
            where[hand] = points[-1]
            move(T.lift, f"{hand} up", {hand: points[-1] + cfg.hover * UP})
        move(T.back, "clear of the desk's edge", {h: clear[h] for h in over})
        move(T.rise, "return", dict(home))
        move(T.rest, "stand", dict(home))
        return Plan(phases=phases, x0=stand.x0, scene=self.scene(params), context={"touches": touches})

    # -- checks ----------------------------------------------------------------------------------

    def touches(self, params: dict[str, float]) -> list[Touch]:
        return self.plan(params).context["touches"]

    def reference_profile(self, traj: Trajectory, hand: str) -> np.ndarray:
        return force_profile(traj.time, self.touches(traj.params), hand, traj.params["force"], self.config.force_ramp)

    def task_errors(self, traj: Trajectory) -> dict[str, dict[str, Any]]:
        th = self.config.thresholds
        mu = self.robot.config.friction_coefficient
        names, ee = list(traj.contact_names), list(traj.ee_names)
        force_err = friction = off = 0.0
        expert = expert_normal_forces(self.robot, traj, self.config.expert_force_window)
        expert_errors = []
        for hand in HANDS:
            c = names.index(hand)
            on = traj.contact_active[:, c]
            f = traj.contact_wrench[:, c, :3]
            profile = self.reference_profile(traj, hand)
            force_err = max(force_err, float(np.max(np.abs(f[on, 2] - profile[on]), initial=0.0)))
            ft = np.linalg.norm(f[on, :2], axis=1)
            friction = max(friction, float(np.max(np.maximum(ft - mu * f[on, 2], -f[on, 2]), initial=0.0)))
            height = traj.ee_pos[on, ee.index(hand), 2] - traj.params["desk_height"] - contact_radius(self.robot, "left_hand")
            off = max(off, 1e3 * float(np.max(np.abs(height), initial=0.0)))
            # the replay's frames are the record's steps (one fewer than its frames); after a fall
            # the expert presses with nothing
            measured = np.zeros(len(profile))
            measured[: len(expert[hand])] = expert[hand]
            pressed = profile >= 1.0
            expert_errors.append(np.abs(measured[pressed] - profile[pressed]))
        errors = np.concatenate(expert_errors)
        return {
            "force_error": {"value": force_err, "limit": th.force_error, "unit": "N"},
            "hand_friction": {"value": friction, "limit": th.hand_friction, "unit": "N"},
            "hand_off_surface": {"value": off, "limit": th.hand_off_surface, "unit": "mm"},
            "expert_force_error": {"value": float(np.mean(errors)) if len(errors) else 0.0, "limit": th.expert_force_error, "unit": "N"},
        }


def sensor_mean(frames: np.ndarray, window: float = SENSOR_WINDOW) -> np.ndarray:
    """A force sensor's view of 200 Hz force frames: the mean over `window` s centred on each frame
    (shorter at the ends). The hand bounces on the stiff desk at tens of Hz: in MuJoCo its contact force
    decays from the impact over some 20 ms, the hand leaves the desk, the arm's servos bring it back.
    The optimizer's feedback expert, 15 N at a wipe's plateau, measures 2.8 to 3.4 N from the reference
    on 5-ms frames and 0.7 to 0.9 N on 50-ms means."""
    frames = np.asarray(frames, dtype=float)
    width = max(1, int(round(window / FRAME_DT)))
    if width == 1 or len(frames) == 0:
        return frames.copy()
    kernel = np.ones(width)
    return np.convolve(frames, kernel, mode="same") / np.convolve(np.ones(len(frames)), kernel, mode="same")


def expert_normal_forces(robot, traj: Trajectory, window: float = 0.05) -> dict[str, np.ndarray]:
    """Per 200 Hz step of the record, each hand's normal force on the desk (N) in MuJoCo when the
    optimizer's feedback expert plays the record with the real desk, until a fall: the mean over
    `window` s centred on the step (`sensor_mean`). A record without the solver's gains is played open loop."""
    from opt2skill.data.replay import Replayer

    replayer = Replayer(robot, traj)
    states = replayer.feedback_states()
    if states is None:
        nstep = int(round(traj.duration / replayer.dt))
        init = replayer.initial_state(0)[None]
        _, sensors = mujoco.rollout.rollout(replayer.model, replayer.data, init, replayer.controls(0, nstep)[None])
        sensors = sensors[0]
    else:
        sensors = states[1]
    per = int(round(FRAME_DT / replayer.dt))
    frames = len(sensors) // per
    force = replayer.layout.point_force(sensors[: frames * per])  # (steps, npoint, 3), on the robot
    names = replayer.layout.point_names
    return {h: sensor_mean(force[:, names.index(h), 2].reshape(frames, per).mean(axis=1), window) for h in HANDS}


def wipe_metrics(reference: Trajectory, tracked: Trajectory) -> dict[str, tuple[float, str]]:
    """Table IV's errors until a fall: the hands' normal force error (N, mean over the frames where the
    reference's hand is on the desk) as a force sensor sees both forces (`force_error`: 50-ms means,
    `sensor_mean`, as in the dataset's check of the expert) and on the 5-ms frames (`force_error_raw`:
    each policy step's mean over its physics steps), and each hand's position error (cm, every frame)."""
    n = tracked.num_frames
    names, ee = list(reference.contact_names), list(reference.ee_names)
    out: dict[str, tuple[float, str]] = {}
    errors, raw = [], []
    for hand in HANDS:
        c = names.index(hand)
        on = reference.contact_active[:n, c]
        ref_force, force = reference.contact_wrench[:n, c, 2], tracked.contact_wrench[:, c, 2]
        errors.append(np.abs(sensor_mean(force) - sensor_mean(ref_force))[on])  # both through the one sensor
        raw.append(np.abs(force - ref_force)[on])
        e = ee.index(hand)
        gap = np.linalg.norm(tracked.ee_pos[:, e] - reference.ee_pos[:n, e], axis=-1)
        out[f"{hand.split('_')[0]}_hand_error"] = (100.0 * float(gap.mean()), "cm")
    for name, parts in (("force_error", errors), ("force_error_raw", raw)):
        values = np.concatenate(parts)
        out[name] = (float(values.mean()) if len(values) else 0.0, "N")
    return out


INFO = TaskInfo(
    name="wipe",
    summary="draw two lines on a desk with the right hand and wipe them with the left, pressing with a "
            "prescribed force (paper Table IV)",
    task=WipeTask,
    params=PARAMS,
    demo_ranges={"force": (10.0, 20.0)},
    metrics=wipe_metrics,
)
