"""The walking gait of a robot for a set of walk parameters: the keypoints every walk source shares.

The TO walk (`trajopt.walk`) and the IK walk (`baselines.ik_walk`) both take their footholds, swing
references, step timing and CoM/heading path from here, so a TO walk and an IK walk of the same
parameters have the same keypoints.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import pinocchio as pin

from opt2skill.model.robot import Robot
from opt2skill.trajopt.config import require
from opt2skill.trajopt.gait import Foothold, GaitPlan, GaitSpec, plan_gait

FEET = ("left_foot", "right_foot")


class GaitTiming(Protocol):
    """The config fields a walk's gait depends on (both walk configs have them)."""

    duration: float
    steps: int
    stand_start: float
    stand_end: float
    ramp: float
    base_height: float


def check_gait_timing(cfg: GaitTiming) -> None:
    """The checks of the gait fields, shared by both walk configs."""
    require(1.0 <= cfg.duration <= 60.0, f"duration = {cfg.duration:g} s must be in [1, 60] s")
    require(cfg.steps >= 0, "steps must be >= 0 (0: fit the duration)")
    require(cfg.stand_start >= 0.05 and cfg.stand_end >= 0.1, "stand_start >= 0.05 s and stand_end >= 0.1 s")
    require(cfg.ramp >= 0, "ramp must be >= 0 s")
    require(-0.2 <= cfg.base_height <= 0.05, "base_height must be in [-0.2, 0.05] m")


def stand_footholds(robot: Robot) -> tuple[dict[str, Foothold], np.ndarray]:
    """The feet's sole placements and the CoM of the robot's stand pose (Pinocchio)."""
    pm = robot.pin_model
    data = pm.createData()
    q0 = robot.stand_q_pin
    pin.framesForwardKinematics(pm, data, q0)
    feet = {}
    for name in FEET:
        placement = data.oMf[robot.pin_frame_id(robot.config.end_effectors[name])]
        feet[name] = Foothold(name, placement.translation.copy(), 0.0)
    return feet, pin.centerOfMass(pm, data, q0)


def walk_gait(robot: Robot, cfg: GaitTiming, params: dict[str, float]) -> tuple[GaitPlan, dict[str, Foothold]]:
    """The gait plan of walk `params` (speed, clearance, step timing, ...) and the stand footholds."""
    feet, com0 = stand_footholds(robot)
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
    return plan_gait(spec, feet, com0[:2].copy()), feet
