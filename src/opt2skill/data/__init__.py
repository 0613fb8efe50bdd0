"""Trajectory records: the contract between trajectory optimization and everything downstream."""

from opt2skill.data.record import Trajectory, build_trajectory

__all__ = ["Trajectory", "build_trajectory"]
