"""Desk reach with an elbow support (paper Sec. IV-E, Fig. 5d): reach beyond the support polygon.

The robot stands at a desk (top at `desk_height`). The paper's five phases:

1. the right hand moves to its target on the desk, the right elbow above its support point;
2. the right elbow comes down on the desk, at rest, and holds contact: a 3D point contact (the
   elbow's site, inside the arm's capsules) with a friction cone along the desk's normal and a least
   normal force (`elbow_min_force`), so it carries part of the robot; it leans on the desk rather
   than pushing along it (the feet would balance that push, and in MuJoCo they creep under it);
3. the left hand reaches its target (`target_x` ahead of the base, beyond the feet) and returns;
4. the CoM comes back over the feet and the elbow unloads to its least force while it still holds,
   then the elbow releases (lifts off the desk);
5. the torso and hands return to the stand pose.

Checks: the hands at their targets (`hand_error`, cm: the left at the reach's end, the right at the
end of phase 1), the elbow's force in the robot's friction cone (`elbow_friction`, N) and the elbow
on the desk top while in contact (`elbow_off_surface`, mm).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.tasks import TaskInfo
from opt2skill.trajopt.config import require
from opt2skill.trajopt.params import Param
from opt2skill.trajopt.phases import Contact, Knot, Phase
from opt2skill.trajopt.phase_task import Plan
from opt2skill.trajopt.skills.desk import DeskConfig, DeskTask, Stand, StandingCosts
from opt2skill.trajopt.skills.manipulation import HandPath, contact_radius, normal_frame

HANDS = ("left_hand", "right_hand")
ELBOW = "right_elbow"
MOVING = HANDS + (ELBOW,)
UP = np.array([0.0, 0.0, 1.0])

PARAMS = (
    Param("desk_height", allowed=(0.5, 1.5), default_range=(0.90, 1.00), unit="m", help="desk top above the floor"),
    Param("target_x", allowed=(0.4, 0.9), default_range=(0.60, 0.70), unit="m",
          help="the reaching (left) hand's target ahead of the base"),
    Param("target_y", allowed=(-0.2, 0.5), default_range=(0.05, 0.25), unit="m", help="its target's y (left +)"),
    Param("target_z", allowed=(0.03, 0.3), default_range=(0.06, 0.12), unit="m", help="its target above the desk top"),
)


@dataclass(frozen=True)
class Timing:
    """Seconds of each phase (multiples of the 5-ms frame)."""

    stand: float = 0.3
    rise: float = 0.4  # a hand up to the height it crosses the desk's edge at, or down from it
    place: float = 1.0  # phase 1: the right hand to its target
    lean: float = 0.5  # the elbow down onto the desk
    reach: float = 1.2  # phase 3: out ...
    hold: float = 0.3
    back: float = 1.2  # ... and back
    settle: float = 0.6  # the CoM back over the feet, the elbow still down
    release: float = 0.5  # phase 4: the elbow up
    home: float = 1.0  # phase 5
    rest: float = 0.4

    def check(self) -> None:
        require(all(0.005 <= v <= 5.0 for v in vars(self).values()), "timing: every phase must last 0.005 to 5 s")


@dataclass(frozen=True)
class ReachWeights:
    paths: float = 1e4  # end effectors along their paths
    target: float = 1e6  # the hands at their targets (the phases' ends)
    touch: float = 1e6  # the elbow where it touches the desk (impulse node)
    still: float = 1e4  # ... and at rest there (a hard touchdown's impulse made the feet slip 6 to 8 mm)
    landing: float = 1e4  # the elbow's velocity entering its touchdown impulse
    com: float = 1e3  # CoM over the middle of the feet (standing phases)
    com_supported: float = 1e2  # ... while the elbow carries part of the robot
    base_orientation: float = 1e3
    feet: float = 1e-2  # each foot's wrench towards half the weight (skills.desk.StandingCosts)
    leaning: float = 1e2  # torso orientation while the elbow is down
    clearance: float = 1e6  # the left elbow above the desk top (no collisions in the optimizer otherwise)
    elbow_sideways: float = 1.0  # per N^2: the resting elbow's force along the desk (the feet balance it)
    unload: float = 1.0  # per N^2: the elbow's normal force towards elbow_min_force before it lifts

    def check(self) -> None:
        require(all(v >= 0 for v in vars(self).values()), "desk reach weights must be >= 0")


@dataclass(frozen=True)
class ReachThresholds:
    hand_error: float = 2.0  # cm, each hand from its target at its phase's end
    elbow_friction: float = 1.0  # N, elbow force outside the robot's friction cone
    elbow_off_surface: float = 3.0  # mm, elbow from the desk top while in contact

    def check(self) -> None:
        require(all(v > 0 for v in vars(self).values()), "desk reach thresholds must be > 0")


@dataclass(frozen=True)
class DeskReachConfig(DeskConfig):
    desk_depth: float = 0.8  # m: the far target stays over it
    reachable: tuple[float, float] = (0.85, 1.05)  # m, desk tops the elbow rests on standing
    elbow_at: tuple[float, float] = (0.33, -0.22)  # m, the elbow's support point ahead of / beside the base
    # m, the right hand's target (x, y ahead; z above the desk): where the forearm lies with the elbow on
    # its support point (at (0.55, -0.12, 0.06) the elbow could not reach that point with the hand
    # there, and the plan swung both forward at 0.7 m/s in the last 0.1 s before the touchdown)
    support_hand: tuple[float, float, float] = (0.66, -0.07, 0.09)
    hover: float = 0.04  # m above its support point before the elbow comes down
    elbow_min_force: float = 5.0  # N, the least normal force on the resting elbow
    timing: Timing = field(default_factory=Timing)
    weights: ReachWeights = field(default_factory=ReachWeights)
    thresholds: ReachThresholds = field(default_factory=ReachThresholds)

    def check_own(self) -> None:
        require(self.elbow_at[0] > self.desk_gap, "elbow_at's x must be beyond the desk's front edge (desk_gap)")
        require(0.0 <= self.elbow_min_force <= 100.0, "elbow_min_force must be in [0, 100] N")
        require(0.01 <= self.hover <= 0.2, "hover must be in [0.01, 0.2] m")
        super().check_own()
        for section in (self.timing, self.weights, self.thresholds):
            section.check()


@dataclass(frozen=True)
class Moments:
    """When things happen (s): the right hand at its target, the elbow's contact, the left at its target."""

    placed: float
    support: tuple[float, float]
    reached: float


class DeskReachTask(DeskTask):
    name = "desk_reach"
    config_class = DeskReachConfig
    params = PARAMS
    doing = "rest its elbow"

    def targets(self, params: dict[str, float]) -> dict[str, np.ndarray]:
        """The elbow's support point (its site resting on the desk), the right hand's and the left's targets."""
        cfg, base, h = self.config, self.robot.stand_q_pin, params["desk_height"]
        sx, sy, sz = cfg.support_hand
        return {
            ELBOW: np.array([base[0] + cfg.elbow_at[0], base[1] + cfg.elbow_at[1], h + contact_radius(self.robot, ELBOW)]),
            "right_hand": np.array([base[0] + sx, base[1] + sy, h + contact_radius(self.robot, "right_hand") + sz]),
            "left_hand": np.array([base[0] + params["target_x"], base[1] + params["target_y"], h + params["target_z"]]),
        }

    # -- the plan --------------------------------------------------------------------------------

    def plan(self, params: dict[str, float]) -> Plan:
        self.check_reach(params)
        cfg, w, T = self.config, self.config.weights, self.config.timing
        stand = Stand.of(self.robot)
        standing = StandingCosts(self.robot, stand, w.com, w.base_orientation, w.paths, w.feet)
        goal = self.targets(params)
        above = goal[ELBOW] + cfg.hover * UP
        elbow = Contact(ELBOW, pin.SE3(normal_frame(UP), goal[ELBOW]), flat=False, min_normal_force=cfg.elbow_min_force)
        where = {n: stand.home[n] for n in MOVING}
        elbow_id = self.robot.pin_frame_id(self.robot.config.end_effectors[ELBOW])
        phases: list[Phase] = []
        t = 0.0

        def costs_of(path: HandPath, supported: bool, leaning: bool, ends: dict[str, np.ndarray]):
            def costs(knot: Knot, terms) -> list:
                if knot.kind == "impulse":  # the elbow touches the desk at its support point, at rest
                    site = self.robot.config.end_effectors[ELBOW]
                    # the velocity entering the impact: the lean's last nodes alone left the plan
                    # free to drive the elbow into the desk at 0.4 m/s in the step before it
                    return [("elbow_touch", terms.translation(site, goal[ELBOW]), w.touch),
                            ("elbow_landing", terms.velocity(site, np.zeros(6), (1, 1, 1, 0, 0, 0)), w.landing)]
                names = [n for n in MOVING if not (supported and n == ELBOW)]
                out = standing.along(terms, knot, path, names)
                if supported and terms.nu > 0 and w.elbow_sideways > 0:
                    out.append(("elbow_sideways", terms.contact_force(elbow_id, np.zeros(3), (1, 1, 0)), w.elbow_sideways))
                if supported and not leaning and terms.nu > 0 and w.unload > 0:  # the weight back on the feet
                    least = np.array([0.0, 0.0, cfg.elbow_min_force])
                    out.append(("elbow_unload", terms.contact_force(elbow_id, least, (0, 0, 1)), w.unload))
                out.append(("left_elbow_above", terms.above(self.robot.config.end_effectors["left_elbow"], clearance),
                            w.clearance))
                if leaning:
                    out += standing.balance(terms, com=w.com_supported, upright=w.leaning)
                else:
                    out += standing.balance(terms)
                if knot.time >= path.t0 + path.duration - 0.05:  # the phase's last nodes: at the targets, still
                    sites = self.robot.config.end_effectors
                    for n, p in ends.items():
                        out += [(f"{n}_target", terms.translation(sites[n], p), w.target),
                                (f"{n}_still", terms.velocity(sites[n], np.zeros(6), (1, 1, 1, 0, 0, 0)), w.still)]
                return out
            return costs

        def move(duration: float, label: str, targets: dict[str, np.ndarray], supported: bool = False,
                 leaning: bool | None = None, ends=()):
            nonlocal t
            path = HandPath(dict(where), {**where, **targets}, t, duration)
            contacts = stand.feet + ((elbow,) if supported else ())
            leaning = supported if leaning is None else leaning
            phases.append(Phase(duration, contacts, costs_of(path, supported, leaning, {n: targets[n] for n in ends}), label))
            where.update(targets)
            t += duration

        # Hands cross the desk's front edge only as high as the elbow hovers over the desk: straight
        # from their home (in front of the edge, below the top) to a target they would hit the edge.
        clear = {h: np.array([*stand.home[h][:2], goal[ELBOW][2] + cfg.hover]) for h in HANDS}
        clearance = goal[ELBOW][2] + cfg.hover / 2  # the reaching arm's elbow stays above the desk
        move(T.stand, "stand", {})
        move(T.rise, "right hand up", {"right_hand": clear["right_hand"]})
        move(T.place, "right hand to its target", {"right_hand": goal["right_hand"], ELBOW: above}, ends=("right_hand",))
        placed = t
        move(T.lean, "elbow down", {ELBOW: goal[ELBOW]}, ends=(ELBOW,))
        start = t
        move(T.rise, "left hand up", {"left_hand": clear["left_hand"]}, supported=True)
        move(T.reach, "left hand out", {"left_hand": goal["left_hand"]}, supported=True, ends=("left_hand",))
        reached = t
        move(T.hold, "left hand at its target", {}, supported=True)
        move(T.back, "left hand back", {"left_hand": clear["left_hand"]}, supported=True)
        # the CoM back over the feet while the elbow still holds: it leaves the desk unloaded
        move(T.settle, "weight back on the feet", {}, supported=True, leaning=False)
        support = (start, t)
        move(T.release, "elbow up", {ELBOW: above, "left_hand": stand.home["left_hand"]})
        move(T.home, "right hand back", {"right_hand": clear["right_hand"], ELBOW: stand.home[ELBOW]})
        move(T.rise, "return", {"right_hand": stand.home["right_hand"]})
        move(T.rest, "stand", {})
        return Plan(phases=phases, x0=stand.x0, scene=self.scene(params),
                    context=Moments(placed=placed, support=support, reached=reached))

    # -- checks ----------------------------------------------------------------------------------

    def moments(self, params: dict[str, float]) -> Moments:
        return self.plan(params).context

    def task_errors(self, traj: Trajectory) -> dict[str, dict[str, Any]]:
        th, params = self.config.thresholds, traj.params
        goal, when = self.targets(params), self.moments(params)
        ee = list(traj.ee_names)
        frame = {"right_hand": int(round(when.placed / FRAME_DT)), "left_hand": int(round(when.reached / FRAME_DT))}
        hand_error = max(float(np.linalg.norm(traj.ee_pos[k, ee.index(h)] - goal[h])) for h, k in frame.items())
        c = list(traj.contact_names).index(ELBOW)
        on = traj.contact_active[:, c]
        f = traj.contact_wrench[on, c, :3]
        mu = self.robot.config.friction_coefficient
        friction = float(np.max(np.maximum(np.linalg.norm(f[:, :2], axis=1) - mu * f[:, 2], -f[:, 2]), initial=0.0))
        off = np.abs(traj.ee_pos[on, ee.index(ELBOW), 2] - goal[ELBOW][2])
        return {
            "hand_error": {"value": 100.0 * hand_error, "limit": th.hand_error, "unit": "cm"},
            "elbow_friction": {"value": friction, "limit": th.elbow_friction, "unit": "N"},
            "elbow_off_surface": {"value": 1e3 * float(np.max(off, initial=0.0)), "limit": th.elbow_off_surface, "unit": "mm"},
        }


def reach_metrics(reference: Trajectory, tracked: Trajectory) -> dict[str, tuple[float, str]]:
    """The paper's hand errors (cm, mean over the motion until a fall) and the elbow's normal force
    error (N, over the frames where the reference rests on it)."""
    n = tracked.num_frames
    ee, names = list(reference.ee_names), list(reference.contact_names)
    out = {}
    for hand in HANDS:
        e = ee.index(hand)
        gap = np.linalg.norm(tracked.ee_pos[:, e] - reference.ee_pos[:n, e], axis=-1)
        out[f"{hand.split('_')[0]}_hand_error"] = (100.0 * float(gap.mean()), "cm")
    c = names.index(ELBOW)
    on = reference.contact_active[:n, c]
    err = np.abs(tracked.contact_wrench[on, c, 2] - reference.contact_wrench[:n][on, c, 2])
    out["elbow_force_error"] = (float(err.mean()) if len(err) else 0.0, "N")
    return out


INFO = TaskInfo(
    name="desk_reach",
    summary="rest the right elbow on a desk and reach beyond the support polygon with the left hand (paper Fig. 5d)",
    task=DeskReachTask,
    params=PARAMS,
    demo_ranges={"target_x": (0.6, 0.65)},
    metrics=reach_metrics,
)
