"""The task home: one module per task in this package, each registering itself with one `TaskInfo`.

A task module holds everything about its task: parameters, config (only its own fields; the shared
sections come from `trajopt.task_config.TaskConfig`), scene, phase plan built from shared skills
(`trajopt.skills`), checks, and its `INFO`, which tells the rest of the pipeline what it needs to
know (tracking differences, task metrics, demo ranges). Adding a task is adding a module here; no
other code branches on task names. Modules are found by listing the package.
"""

from __future__ import annotations

import importlib
import pkgutil
from dataclasses import dataclass, field
from functools import lru_cache
from typing import TYPE_CHECKING, Any, Callable

from opt2skill.errors import ConfigError

if TYPE_CHECKING:
    from opt2skill.data.record import Trajectory
    from opt2skill.model.robot import Robot
    from opt2skill.trajopt.params import Param
    from opt2skill.trajopt.task import Task

# (reference, tracked) -> {metric name: (value, unit)}; tracked may be shorter (a fall).
TaskMetrics = Callable[["Trajectory", "Trajectory"], dict[str, tuple[float, str]]]


@dataclass(frozen=True)
class TaskInfo:
    """What the pipeline downstream of trajectory optimization knows about a task."""

    name: str
    summary: str  # one line for help texts
    task: type[Task] | None  # parameters -> trajectory record (None: references come from elsewhere)
    params: tuple[Param, ...]
    # Table I: the base-position reward is left out where the reference's absolute base position
    # is not the skill (walking: drift is measured separately).
    track_base_position: bool = True
    demo_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)  # the demo's sampling ranges
    metrics: TaskMetrics | None = None  # task metrics beside the paper's tracking errors
    made_by: str = "opt2skill generate"  # the command that makes its references


@lru_cache(maxsize=1)
def _registry() -> dict[str, TaskInfo]:
    tasks: dict[str, TaskInfo] = {}
    for module in pkgutil.iter_modules(__path__):
        if module.name.startswith("_"):
            continue
        info = getattr(importlib.import_module(f"{__name__}.{module.name}"), "INFO", None)
        if not isinstance(info, TaskInfo):
            raise ConfigError(f"task module opt2skill.tasks.{module.name} has no INFO = TaskInfo(...)")
        if info.name in tasks:
            raise ConfigError(f"two task modules register the task '{info.name}'")
        tasks[info.name] = info
    return tasks


def available_tasks() -> list[str]:
    return sorted(_registry())


def task_info(name: str) -> TaskInfo:
    """The registration of task `name`; an unknown name is a ConfigError listing the tasks."""
    tasks = _registry()
    if name not in tasks:
        raise ConfigError(f"unknown task '{name}'; tasks: {', '.join(sorted(tasks))}")
    return tasks[name]


def get_task(name: str, robot: Robot, overrides: dict[str, Any] | None = None) -> Task:
    """The task `name` for `robot`, its config defaults replaced by `overrides` (checked)."""
    info = task_info(name)
    if info.task is None:
        raise ConfigError(f"task '{name}' is not generated: its references come from `{info.made_by}`")
    return info.task(robot, overrides)
