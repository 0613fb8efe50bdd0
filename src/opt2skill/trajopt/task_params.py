"""Each task's parameters with their allowed and default sampling ranges.

Kept apart from the tasks (which load Crocoddyl and Pinocchio) so that the command line can list
them in its help at no cost. The task classes take theirs from `TASK_PARAMS`.
"""

from __future__ import annotations

from opt2skill.trajopt.params import Param

SQUAT_PARAMS = (
    Param("depth", allowed=(0.0, 0.2), default_range=(0.0, 0.15), unit="m", help="how far the CoM goes down"),
)

WALK_PARAMS = (
    Param("speed", allowed=(0.0, 1.5), default_range=(0.0, 1.5), unit="m/s", help="forward speed (0: stepping in place)"),
    Param("clearance", allowed=(0.03, 0.3), default_range=(0.10, 0.20), unit="m", help="swing-foot apex height"),
    Param("step_duration", allowed=(0.25, 0.8), default_range=(0.3, 0.4), unit="s", help="one step (gait period / 2)"),
    Param("double_support", allowed=(0.0, 0.5), default_range=(0.1, 0.3), unit="", help="fraction of a step on both feet"),
    Param("lateral_speed", allowed=(-0.3, 0.3), default_range=(0.0, 0.0), unit="m/s", help="sideways speed (left +)"),
    Param("yaw_rate", allowed=(-0.5, 0.5), default_range=(0.0, 0.0), unit="rad/s", help="turning rate (left +)"),
    Param("height_offset", allowed=(-0.15, 0.05), default_range=(-0.05, 0.0), unit="m", help="base height change"),
)

# walk_ik (the IK baseline) samples the walk's space: same seed and index, same parameters.
TASK_PARAMS: dict[str, tuple[Param, ...]] = {"squat": SQUAT_PARAMS, "walk": WALK_PARAMS, "walk_ik": WALK_PARAMS}
