"""Walking (paper Sec. III-A with Sec. IV-B's dataset): stand, accelerate, walk, decelerate, stand.

The locomotion skill (`trajopt.skills.locomotion`) on level ground along a gait plan
(`trajopt.skills.gait`) from the commanded forward, lateral and turning speeds. Checks: the realized
mean velocity against the commanded one, and the swing apex against the requested clearance.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.tasks import TaskInfo
from opt2skill.trajopt.config import require
from opt2skill.trajopt.params import Param
from opt2skill.trajopt.phase_task import Plan
from opt2skill.trajopt.settings import SolverSettings
from opt2skill.trajopt.skills.gait import Foothold, GaitPlan, GaitSpec, plan_gait
from opt2skill.trajopt.skills.locomotion import LocomotionConfig, LocomotionTask, com_xy, locomotion_phases, stand_footholds

PARAMS = (
    Param("speed", allowed=(0.0, 1.5), default_range=(0.0, 1.5), unit="m/s", help="forward speed (0: stepping in place)"),
    Param("clearance", allowed=(0.03, 0.3), default_range=(0.10, 0.20), unit="m", help="swing-foot apex height"),
    Param("step_duration", allowed=(0.25, 0.8), default_range=(0.3, 0.4), unit="s", help="one step (gait period / 2)"),
    Param("double_support", allowed=(0.0, 0.5), default_range=(0.1, 0.3), unit="", help="fraction of a step on both feet"),
    Param("lateral_speed", allowed=(-0.3, 0.3), default_range=(0.0, 0.0), unit="m/s", help="sideways speed (left +)"),
    Param("yaw_rate", allowed=(-0.5, 0.5), default_range=(0.0, 0.0), unit="rad/s", help="turning rate (left +)"),
    Param("height_offset", allowed=(-0.15, 0.05), default_range=(-0.05, 0.0), unit="m", help="base height change"),
)


@dataclass(frozen=True)
class WalkThresholds:
    speed_error: float = 0.1  # m/s, |mean base speed over the cruise - requested|
    clearance_error: float = 0.03  # m, |median swing apex - requested|

    def check(self) -> None:
        require(self.speed_error > 0 and self.clearance_error > 0, "walk thresholds must be > 0")


@dataclass(frozen=True)
class WalkConfig(LocomotionConfig):
    duration: float = 14.0  # s, the whole motion (the paper's dataset)
    steps: int = 0  # number of steps; 0: as many as fit in `duration`
    thresholds: WalkThresholds = field(default_factory=WalkThresholds)
    # A window stops once a full step leaves the part it keeps in place (`commit_tol`, 0.01), and a
    # step no longer than a tenth raises the regularization (`reg_increase_below`, 0.1): together a
    # fifth fewer iterations than running every window to its cap, at +1.6 % plan cost in the median
    # over 20 walks, 98 % of 200 accepted (docs/trajopt.md, "Speed: stopping on the committed part" and
    # "the regularization rule joins the walk's default"); walks made before 2026-12-07 used neither.
    solver: SolverSettings = field(default_factory=lambda: SolverSettings(dt=0.03, max_iter=200, reg_init=1e-4,
                                                                          commit_tol=0.01, reg_increase_below=0.1))

    def check_own(self) -> None:
        super().check_own()
        check_gait_timing(self)
        self.thresholds.check()


def check_gait_timing(cfg) -> None:
    """The checks of the gait fields (duration, steps, stand_start, stand_end, ramp, base_height),
    shared with the IK walk's config (`tasks.walk_ik`)."""
    require(1.0 <= cfg.duration <= 60.0, f"duration = {cfg.duration:g} s must be in [1, 60] s")
    require(cfg.steps >= 0, "steps must be >= 0 (0: fit the duration)")
    require(cfg.stand_start >= 0.05 and cfg.stand_end >= 0.1, "stand_start >= 0.05 s and stand_end >= 0.1 s")
    require(cfg.ramp >= 0, "ramp must be >= 0 s")
    require(-0.2 <= cfg.base_height <= 0.05, "base_height must be in [-0.2, 0.05] m")


def walk_gait(robot, cfg, params: dict[str, float]) -> tuple[GaitPlan, dict[str, Foothold]]:
    """The gait plan of walk `params` and the stand footholds: the keypoints every walk source
    shares (the TO walk here, the IK walk in `tasks.walk_ik`), so both walks of the same
    parameters step on the same footholds with the same timing."""
    feet = stand_footholds(robot, robot.stand_q_pin)
    spec = GaitSpec(
        speed=params["speed"],
        lateral_speed=params["lateral_speed"],
        yaw_rate=params["yaw_rate"],
        clearance=params["clearance"],
        step_duration=params["step_duration"],
        double_support=params["double_support"],
        stand_start=cfg.stand_start,
        duration=cfg.duration,
        stand_end_min=cfg.stand_end,
        ramp=cfg.ramp,
        steps=cfg.steps,
    )
    return plan_gait(spec, feet, com_xy(robot, robot.stand_q_pin)), feet


class WalkTask(LocomotionTask):
    name = "walk"
    config_class = WalkConfig
    params = PARAMS

    def gait(self, params: dict[str, float]) -> tuple[GaitPlan, dict[str, Foothold]]:
        return walk_gait(self.robot, self.config, params)

    def plan(self, params: dict[str, float]) -> Plan:
        gait, feet = self.gait(params)
        x0 = np.concatenate([self.robot.stand_q_pin, np.zeros(self.robot.nv)])
        base_z = x0[2] + self.config.base_height + params["height_offset"]
        phases = locomotion_phases(self.robot, gait, feet, self.config.weights, base_z, params["clearance"])
        return Plan(phases=phases, x0=x0, context=gait)

    def task_errors(self, traj: Trajectory) -> dict[str, dict[str, Any]]:
        return walk_errors(self.gait(traj.params)[0], self.config.thresholds, traj)


def walk_errors(gait: GaitPlan, th: WalkThresholds, traj: Trajectory) -> dict[str, dict[str, Any]]:
    """Realized mean velocity against the commanded one, and swing apexes against the clearance."""
    apex_errors = []
    ee = list(traj.ee_names)
    for step in gait.steps:
        window = slice(int(round(step.liftoff / FRAME_DT)), int(round(step.touchdown / FRAME_DT)) + 1)
        z = traj.ee_pos[window, ee.index(step.swing), 2]
        ground = max(step.origin.position[2], step.target.position[2])
        apex_errors.append(abs(float(z.max()) - ground - traj.params["clearance"]))
    return {
        "speed_error": {"value": speed_error(gait, traj), "limit": th.speed_error, "unit": "m/s"},
        "clearance_error": {"value": float(np.median(apex_errors)), "limit": th.clearance_error, "unit": "m"},
    }


def speed_error(gait: GaitPlan, traj: Trajectory) -> float:
    """|realized - commanded| mean base velocity from the first lift-off to the last touchdown, in
    the heading frame (m/s)."""
    frames = slice(int(round(gait.steps[0].liftoff / FRAME_DT)), int(round(gait.steps[-1].touchdown / FRAME_DT)))
    heading = gait.heading[frames]
    c, s = np.cos(heading), np.sin(heading)

    def in_heading(v: np.ndarray) -> np.ndarray:
        return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1]], 1).mean(0)

    return float(np.linalg.norm(in_heading(traj.qvel[frames, :2]) - in_heading(gait.velocity[frames, :2])))


INFO = TaskInfo(
    name="walk",
    summary="walking at commanded forward, lateral and turning speeds (14 s)",
    task=WalkTask,
    params=PARAMS,
    track_base_position=False,  # Table I: "the Base Pos. reward is not included in walking"
    demo_ranges={"speed": (0.5, 1.0)},  # moderate speeds, which the optimizer accepts most often
)
