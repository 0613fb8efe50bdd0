"""A task is a family of motions: a parameter space and a solver that returns a trajectory record.

Dataset generation (`opt2skill generate <task>`) only uses this interface, so a new task (stairs,
box pickup, ...) is a new `Task` subclass in its own file under `opt2skill.tasks`, not a new pipeline.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

from opt2skill.data.record import Trajectory
from opt2skill.model.robot import Robot
from opt2skill.trajopt.params import ParamSpace


class Task(ABC):
    name: ClassVar[str]
    # What the records are made by: "to" (optimization, with torques and contact forces) or a
    # kinematic source ("ik", "human") whose records have `has_dynamics=False` (docs/baselines.md).
    source: ClassVar[str] = "to"
    has_dynamics: ClassVar[bool] = True

    def __init__(self, robot: Robot, overrides: dict[str, Any] | None = None):
        """`overrides`: values that replace the task config's defaults (unknown keys are errors)."""
        self.robot = robot

    @abstractmethod
    def param_space(self) -> ParamSpace:
        """The task's parameters with their allowed and sampling ranges."""

    @abstractmethod
    def solve(self, params: dict[str, float], seed: int) -> Trajectory:
        """Optimize one motion. Raises `SolverError` when the solver diverges or fails.

        The record carries 200 Hz frames, solver statistics (`solver`) and provenance; validation
        fills `validation` afterwards.
        """

    def task_errors(self, traj: Trajectory) -> dict[str, dict[str, Any]]:
        """Task-specific checks of a solved record (e.g. realized against requested speed).

        name -> {"value": float, "limit": float, "unit": str}; a value above its limit rejects the
        trajectory. Values are non-negative errors. Default: no task-specific checks.
        """
        return {}
