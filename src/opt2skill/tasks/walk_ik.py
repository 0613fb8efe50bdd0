"""The IK walk (`opt2skill generate walk_ik`): the TO walk's keypoints through QP inverse kinematics.

The paper's IK baseline (Sec. IV-B): "generated from hand-designed keypoint sequences (e.g.,
footstep and torso motion), converted to joint angles via QP-based IK". The keypoints are exactly
those the TO walk tracks (`tasks.walk.walk_gait`): footholds, cubic swing-foot splines with the
clearance, step timing, the CoM path and heading, the base height; the arms hold the stand posture.
The parameter space is the walk's, so `walk` and `walk_ik` datasets of the same seed have the same
parameters at every index. Records carry no torques or contact forces (`has_dynamics=False`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from opt2skill.baselines.ik_solver import FEET, FrameTargets, IKSettings, KeypointIK
from opt2skill.baselines.kinematic_record import kinematic_trajectory
from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.model.robot import Robot
from opt2skill.provenance import provenance
from opt2skill.trajopt.config import apply_overrides, config_to_dict
from opt2skill.tasks import TaskInfo
from opt2skill.tasks.walk import PARAMS, WalkConfig, WalkThresholds, check_gait_timing, walk_errors, walk_gait
from opt2skill.trajopt.params import ParamSpace
from opt2skill.trajopt.skills.gait import Foothold, GaitPlan, swing_reference, yaw_matrix
from opt2skill.trajopt.task import Task


@dataclass(frozen=True)
class IKWalkConfig:
    # The gait fields default to the TO walk's, so both walks of the same parameters share keypoints.
    duration: float = WalkConfig.duration
    steps: int = WalkConfig.steps
    stand_start: float = WalkConfig.stand_start
    stand_end: float = WalkConfig.stand_end
    ramp: float = WalkConfig.ramp
    base_height: float = WalkConfig.base_height
    thresholds: WalkThresholds = field(default_factory=WalkThresholds)
    ik: IKSettings = field(default_factory=IKSettings)
    ranges: dict = field(default_factory=dict)

    def check(self) -> None:
        check_gait_timing(self)
        self.thresholds.check()
        self.ik.check()


def foot_placements(gait: GaitPlan, feet: dict[str, Foothold], t: float, clearance: float
                    ) -> tuple[dict[str, tuple[np.ndarray, float]], dict[str, bool]]:
    """Each sole's target (position, yaw) at time t, and whether it is on the ground (stance)."""
    out = {name: (f.position, f.yaw) for name, f in feet.items()}
    stance = {name: True for name in feet}
    for step in gait.steps:
        if step.liftoff > t + 1e-9:
            break
        if t < step.touchdown - 1e-9:  # in the air: lift-off frame included, touchdown frame on the ground
            position, yaw, _ = swing_reference(step, t, clearance)
            out[step.swing], stance[step.swing] = (position, yaw), False
        else:
            out[step.swing] = (step.target.position, step.target.yaw)
    return out, stance


class IKWalkTask(Task):
    name = "walk_ik"
    source = "ik"
    has_dynamics = False

    def __init__(self, robot: Robot, overrides: dict[str, Any] | None = None):
        super().__init__(robot, overrides)
        self.config = apply_overrides(IKWalkConfig(), overrides)
        self.param_space()

    def param_space(self) -> ParamSpace:
        return ParamSpace(list(PARAMS), ranges=self.config.ranges)

    def gait(self, params: dict[str, float]) -> tuple[GaitPlan, dict[str, Foothold]]:
        return walk_gait(self.robot, self.config, params)

    def keypoints(self, params: dict[str, float]) -> tuple[list[FrameTargets], np.ndarray]:
        """The targets of every 200 Hz frame and the contact schedule (T, 2) of the feet."""
        gait, feet = self.gait(params)
        base_z = self.robot.stand_q_pin[2] + self.config.base_height + params["height_offset"]
        targets, active = [], np.zeros((len(gait.times), len(FEET)), dtype=bool)
        for k, t in enumerate(gait.times):
            placements, stance = foot_placements(gait, feet, float(t), params["clearance"])
            heading = float(gait.heading[k])
            targets.append(FrameTargets(
                feet={f: (np.asarray(p, dtype=float), yaw_matrix(y)) for f, (p, y) in placements.items()},
                base_rotation=yaw_matrix(heading),
                base_position=np.array([0.0, 0.0, base_z]),
                base_axes=(0.0, 0.0, 1.0),
                com_xy=gait.com_xy[k],
            ))
            active[k] = [stance[f] for f in FEET]
        return targets, active

    def solve(self, params: dict[str, float], seed: int) -> Trajectory:
        start = time.perf_counter()
        params = self.param_space().check(params)
        targets, active = self.keypoints(params)
        result = KeypointIK(self.robot, self.config.ik).solve(targets)
        solve_time = time.perf_counter() - start
        stats = {
            "name": f"QP differential IK (mink, {self.config.ik.solver})",
            "iterations": int(result.iterations.sum()),
            "iterations_per_frame_max": int(result.iterations.max()),
            "converged": bool(result.foot_error.max() < self.config.ik.tolerance),
            "foot_error_max": float(result.foot_error.max()),
            "foot_error_mean": float(result.foot_error.mean()),
            "solve_time": solve_time,
            "frame_dt": FRAME_DT,
        }
        traj = kinematic_trajectory(
            self.robot, result.qpos, active, task=self.name, source=self.source, contact_names=FEET,
            params=params, seed=seed, solver=stats,
            provenance=provenance(self.robot.hash, task_config=config_to_dict(self.config)),
        )
        traj.solver["total_time"] = time.perf_counter() - start
        return traj

    def task_errors(self, traj: Trajectory) -> dict[str, dict[str, Any]]:
        errors = walk_errors(self.gait(traj.params)[0], self.config.thresholds, traj)
        errors["ik_foot_error"] = {"value": float(traj.solver.get("foot_error_max", 0.0)), "limit": 0.005, "unit": "m"}
        return errors


INFO = TaskInfo(
    name="walk_ik",
    summary="the IK baseline: the walk's keypoints through QP inverse kinematics, no dynamics (docs/baselines.md)",
    task=IKWalkTask,
    params=PARAMS,
    track_base_position=False,  # trained as the TO walk is (Table I)
    demo_ranges={"speed": (0.5, 1.0)},
)
