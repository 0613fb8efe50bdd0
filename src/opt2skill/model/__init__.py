"""The robot in MuJoCo and Pinocchio, and the conversions between their conventions."""

from opt2skill.model.robot import Robot, load_robot

__all__ = ["Robot", "load_robot"]
