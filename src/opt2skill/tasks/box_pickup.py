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

The scene, the config fields and the phases are the box-handling skill's
(`trajopt.skills.box_handling`: `take` is phases 1 to 3 and the way out past the board's edge,
`put` the rest), shared with the
pickup-then-walk task (`tasks.box_walk`).

Checks: the hands' friction cones at the box, and the optimizer's feedback expert in MuJoCo with the
real shelf and box must put the box within 3 cm of its target (`placement_error`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from opt2skill.data.record import Trajectory
from opt2skill.errors import ConfigError
from opt2skill.tasks import TaskInfo
from opt2skill.trajopt.config import require
from opt2skill.trajopt.params import Param
from opt2skill.trajopt.phase_task import Plan
from opt2skill.trajopt.skills.box_handling import (BoxHandlingConfig, BoxHandlingTask, expert_box_pose,
                                                   hand_friction_violation)

PARAMS = (
    Param("low", allowed=(0.3, 0.95), default_range=(0.84, 0.90), unit="m", help="lower board's top"),
    Param("high", allowed=(0.8, 1.45), default_range=(1.20, 1.30), unit="m", help="upper board's top"),
    Param("upward", allowed=(0.0, 1.0), default_range=(0.0, 1.0), unit="", help="from 0.5: low to high; below: high to low"),
    Param("reach", allowed=(0.35, 0.6), default_range=(0.49, 0.53), unit="m", help="box centre ahead of the base"),
    Param("box_width", allowed=(0.2, 0.4), default_range=(0.27, 0.32), unit="m", help="box extent between the hands"),
    Param("box_mass", allowed=(0.0, 5.0), default_range=(0.3, 1.0), unit="kg", help="box mass"),
)


@dataclass(frozen=True)
class BoxThresholds:
    hand_friction: float = 1.0  # N, largest hand force outside the hand-box friction cone
    placement_error: float = 0.03  # m, the box's final centre from its target, expert in MuJoCo
    placement_tilt: float = 10.0  # deg, the box's final turn from upright at its yaw, expert in MuJoCo

    def check(self) -> None:
        require(self.hand_friction > 0 and self.placement_error > 0 and self.placement_tilt > 0,
                "box thresholds must be > 0")


@dataclass(frozen=True)
class BoxPickupConfig(BoxHandlingConfig):
    thresholds: BoxThresholds = field(default_factory=BoxThresholds)

    def check_own(self) -> None:
        super().check_own()
        self.thresholds.check()


class BoxPickupTask(BoxHandlingTask):
    name = "box_pickup"
    config_class = BoxPickupConfig
    params = PARAMS

    def boards(self, params: dict[str, float]) -> tuple[float, float]:
        """(source, target) board heights; a ConfigError when the box would not fit under the upper."""
        low, high = params["low"], params["high"]
        if high - low < self.config.box_height + self.config.board_gap:
            raise ConfigError(f"boards low = {low:g} m and high = {high:g} m are too close: the box "
                              f"({self.config.box_height:g} m) and the hands need "
                              f"{self.config.box_height + self.config.board_gap:g} m between them")
        return (low, high) if params["upward"] >= 0.5 else (high, low)

    def shelf_boards(self, params: dict[str, float]) -> tuple[float, ...]:
        return self.boards(params)

    def source_board(self, params: dict[str, float]) -> float:
        return self.boards(params)[0]

    def put_target(self, params: dict[str, float]) -> np.ndarray:
        return self.box_centres(params)[1]

    def box_centres(self, params: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        source, target = self.boards(params)
        return self.box_centre(params, source), self.box_centre(params, target)

    def plan(self, params: dict[str, float]) -> Plan:
        source, target = self.boards(params)
        phases = self.box_phases(params)
        phases.put(phases.take(source), target)
        x0 = np.concatenate([self.robot.stand_q_pin, np.zeros(self.robot.nv)])
        return Plan(phases=phases.phases, x0=x0, scene=self.scene(params), context=params)

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


INFO = TaskInfo(
    name="box_pickup",
    summary="pick a box up from one shelf board and place it on another (paper Sec. IV-E)",
    task=BoxPickupTask,
    params=PARAMS,
    demo_ranges={"box_mass": (0.3, 0.6), "upward": (0.6, 1.0)},
)
