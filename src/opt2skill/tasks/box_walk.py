"""Pickup then walk: take a box from a shelf board with both hands, then walk away carrying it.

Composed from two skills, nothing copied: the box pickup's first phases (`skills.box_handling`,
`BoxPhases.take`: stand, squat and reach, reach in, close, squeeze, lift and retract, out past the
board's front edge), then the locomotion skill's phases (`skills.locomotion.locomotion_phases` along
a gait plan from `skills.gait`) with the box held on every node (`BoxPhases.carry`): half its mass
at each hand, the squeeze inside the solve, the hands kept where they held the box moved along the
planned CoM path. The robot walks backwards, away from the shelf (it stands in front of the robot:
forwards the torso would meet its boards), `steps` steps covering `distance`, and stands with the
box.

Checks: the hands' friction cones at the box; the walk (the realized base displacement against the
planned one, the swing apexes against the clearance); and the optimizer's feedback expert in MuJoCo
with the real shelf and the box held by friction alone must carry the box: its centre within
`carry_error` of the reference's box at every frame from the grasp to the end.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.errors import ConfigError
from opt2skill.tasks import TaskInfo
from opt2skill.tasks.walk import WalkThresholds, walk_errors
from opt2skill.trajopt.config import require
from opt2skill.trajopt.params import Param, ParamSpace
from opt2skill.trajopt.phase_task import Plan
from opt2skill.trajopt.phases import Problem
from opt2skill.trajopt.posture import Posture
from opt2skill.trajopt.settings import SolverSettings
from opt2skill.trajopt.skills.box_handling import (HANDS, BoxHandlingConfig, BoxHandlingTask, expert_box_path,
                                                   hand_friction_violation)
from opt2skill.trajopt.skills.gait import GaitPlan, GaitSpec, plan_gait
from opt2skill.trajopt.skills.locomotion import (LocomotionWeights, com_xy, locomotion_phases, solve_walk,
                                                 stand_footholds)
from opt2skill.trajopt.solver import Solution

PARAMS = (
    Param("board", allowed=(0.75, 1.3), default_range=(0.84, 0.95), unit="m", help="the box's board's top"),
    Param("reach", allowed=(0.35, 0.6), default_range=(0.49, 0.53), unit="m", help="box centre ahead of the base"),
    Param("box_width", allowed=(0.2, 0.4), default_range=(0.27, 0.32), unit="m", help="box extent between the hands"),
    Param("box_mass", allowed=(0.1, 5.0), default_range=(0.3, 1.0), unit="kg", help="box mass"),
    Param("distance", allowed=(0.05, 1.0), default_range=(0.12, 0.2), unit="m", help="walked backwards, away from the shelf"),
    Param("steps", allowed=(2, 8), default_range=(2.51, 4.49), unit="", help="number of steps, rounded to an integer"),
    Param("step_duration", allowed=(0.3, 0.8), default_range=(0.4, 0.5), unit="s", help="one step (gait period / 2)"),
    Param("clearance", allowed=(0.03, 0.2), default_range=(0.06, 0.10), unit="m", help="swing-foot apex height"),
)


@dataclass(frozen=True)
class BoxWalkThresholds:
    hand_friction: float = 1.0  # N, largest hand force outside the hand-box friction cone
    carry_error: float = 0.05  # m, the box's centre from the reference's, expert in MuJoCo, grasp to end
    distance_error: float = 0.05  # m, |realized base displacement - planned CoM displacement|
    speed_error: float = 0.1  # m/s, mean base velocity over the walk against the planned one
    clearance_error: float = 0.03  # m, |median swing apex - clearance|

    def check(self) -> None:
        require(all(v > 0 for v in vars(self).values()), "box_walk thresholds must be > 0")


@dataclass(frozen=True)
class BoxWalkConfig(BoxHandlingConfig):
    stand_start: float = 0.3  # s standing with the box before the first step
    stand_end: float = 0.8  # s (at least) standing after the last step
    ramp: float = 1.5  # s to reach the walking speed, and to stop (capped by the gait's length)
    double_support: float = 0.2  # fraction of a step on both feet
    base_height: float = 0.0  # m, walking base height relative to standing
    max_speed: float = 0.6  # m/s, the walking speed `distance` in `steps` may ask for at most
    # CoM along the planned path ten times walking's: at 1e2 it lagged the plan by 4 to 6 cm.
    walk_weights: LocomotionWeights = field(default_factory=lambda: LocomotionWeights(com_path=1e3))
    # The steps' posture (the pickup keeps `posture`'s stiff legs): with the pickup's, the swing
    # feet rose 2 cm of 9; with these soft legs everywhere the pickup dipped and the expert fell.
    # Soft arms too: the terminal node's posture (100 times heavier) pulled the arms towards the
    # stand pose's, and with the hands held on the box the torso leaned 4 cm forward at the end.
    walk_posture: Posture = field(default_factory=lambda: Posture(legs=0.3, leg_velocity=0.3, arms=0.3, base_velocity=1.0))
    thresholds: BoxWalkThresholds = field(default_factory=BoxWalkThresholds)
    # The expert's gains from one regularized Riccati pass over the whole motion: the receding
    # windows' own gains jumped 30 times (norm 800 to 29,500) where the last, shorter window
    # began, and the expert's feet slid 17 to 23 cm or it fell in the final stand (docs/trajopt.md).
    solver: SolverSettings = field(default_factory=lambda: SolverSettings(dt=0.02, max_iter=200, reg_init=1e-4,
                                                                          gains="riccati"))

    def check_own(self) -> None:
        super().check_own()
        require(self.stand_start >= 0.05 and self.stand_end >= 0.1, "stand_start >= 0.05 s and stand_end >= 0.1 s")
        require(self.ramp >= 0 and 0.0 <= self.double_support <= 0.5, "ramp >= 0 s, double_support in [0, 0.5]")
        require(-0.2 <= self.base_height <= 0.05, "base_height must be in [-0.2, 0.05] m")
        require(0.0 < self.max_speed <= 1.0, "max_speed must be in (0, 1] m/s")
        self.walk_weights.check()
        self.walk_posture.check()
        self.thresholds.check()


class BoxWalkTask(BoxHandlingTask):
    name = "box_walk"
    config_class = BoxWalkConfig
    params = PARAMS

    def param_space(self) -> ParamSpace:
        """The parameters; sampling ranges whose longest distance in the fewest, shortest steps
        needs more than `max_speed` are refused here, before any solve."""
        space = super().param_space()
        r = space.ranges
        corner = {"distance": r["distance"][1], "steps": r["steps"][0], "step_duration": r["step_duration"][0],
                  "clearance": r["clearance"][0]}
        try:
            self.gait(corner, after=0.0)  # the speed a walk needs does not depend on when it starts
        except ConfigError as exc:
            raise ConfigError(f"the sampling ranges reach a walk too fast: {exc}") from None
        return space

    def shelf_boards(self, params: dict[str, float]) -> tuple[float, ...]:
        return (params["board"],)

    def source_board(self, params: dict[str, float]) -> float:
        return params["board"]

    def gait(self, params: dict[str, float], after: float) -> GaitPlan:
        """The walk backwards from the stand footholds, its first step `stand_start` after `after`
        (the pickup's end), at the speed that covers `distance` in `steps` steps."""
        cfg = self.config
        feet = stand_footholds(self.robot, self.robot.stand_q_pin)

        def plan(speed: float) -> GaitPlan:
            spec = GaitSpec(speed=speed, lateral_speed=0.0, yaw_rate=0.0, clearance=params["clearance"],
                            step_duration=params["step_duration"], double_support=cfg.double_support,
                            stand_start=after + cfg.stand_start, duration=0.0, stand_end_min=cfg.stand_end,
                            ramp=cfg.ramp, steps=int(round(params["steps"])))
            return plan_gait(spec, feet, com_xy(self.robot, self.robot.stand_q_pin))

        unit = plan(-1.0)  # the CoM path is linear in the speed
        per_speed = float(np.linalg.norm(unit.com_xy[-1] - unit.com_xy[0]))
        speed = params["distance"] / per_speed
        if speed > cfg.max_speed:
            raise ConfigError(f"distance = {params['distance']:g} m in {int(round(params['steps']))} steps of "
                              f"{params['step_duration']:g} s needs {speed:.2f} m/s, more than max_speed "
                              f"{cfg.max_speed:g} m/s: take more or longer steps, or a shorter distance "
                              f"(at most {cfg.max_speed * per_speed:.2f} m)")
        return plan(-speed)

    def plan(self, params: dict[str, float]) -> Plan:
        cfg = self.config
        box = self.box_phases(params)
        held_at = box.take(params["board"])
        gait = self.gait(params, after=box.t)
        feet = stand_footholds(self.robot, self.robot.stand_q_pin)
        x0 = np.concatenate([self.robot.stand_q_pin, np.zeros(self.robot.nv)])
        start = gait.sample(box.t)[0]

        def hands(t: float) -> dict[str, np.ndarray]:
            moved = np.r_[gait.sample(t)[0] - start, 0.0]  # the box goes where the planned CoM goes
            return {h: p + moved for h, p in held_at.items()}

        walking = locomotion_phases(self.robot, gait, feet, cfg.walk_weights, x0[2] + cfg.base_height,
                                    params["clearance"], after=box.t)
        for phase in walking:
            box.carry(dataclasses.replace(phase, posture=cfg.walk_posture), hands)
        return Plan(phases=box.phases, x0=x0, scene=self.scene(params), context=params)

    def optimize(self, problem: Problem, plan: Plan) -> Solution:
        rc = self.config.receding
        if not rc.enabled:
            return super().optimize(problem, plan)
        return solve_walk(problem, self.config.solver, rc, self.walk_of(plan.context))

    def walk_of(self, params: dict[str, float]) -> GaitPlan:
        """The gait of a plan (or a record) of `params`: after the pickup's phases."""
        return self.gait(params, after=self.box_phases_end(params))

    def box_phases_end(self, params: dict[str, float]) -> float:
        box = self.box_phases(params)
        box.take(params["board"])
        return box.t

    def task_errors(self, traj: Trajectory) -> dict[str, dict[str, Any]]:
        th = self.config.thresholds
        gait = self.walk_of(traj.params)
        walk = walk_errors(gait, WalkThresholds(th.speed_error, th.clearance_error), traj)
        # the base's displacement over the walk against the planned CoM's
        first = int(round(gait.steps[0].liftoff / FRAME_DT))
        planned = gait.com_xy[-1] - gait.com_xy[first]
        moved = traj.qpos[-1, :2] - traj.qpos[first, :2]
        # the box in MuJoCo against the reference's box, from the grasp (both hands on it) to the end
        hands = [list(traj.contact_names).index(h) for h in HANDS]
        grasp = int(np.flatnonzero(traj.contact_active[:, hands].all(axis=1))[0])
        path = expert_box_path(self.robot, traj, "box")
        carry = np.linalg.norm(path[grasp:, :3] - traj.prop_poses["box"][grasp : len(path), :3], axis=1)
        mu = self.robot.config.friction_coefficient
        return {
            "hand_friction": {"value": hand_friction_violation(traj, mu), "limit": th.hand_friction, "unit": "N"},
            "carry_error": {"value": float(carry.max(initial=0.0)), "limit": th.carry_error, "unit": "m"},
            "distance_error": {"value": float(np.linalg.norm(moved - planned)), "limit": th.distance_error, "unit": "m"},
            **walk,
        }


INFO = TaskInfo(
    name="box_walk",
    summary="take a box from a shelf board with both hands, then walk backwards carrying it",
    task=BoxWalkTask,
    params=PARAMS,
    demo_ranges={"box_mass": (0.3, 0.6)},
)
