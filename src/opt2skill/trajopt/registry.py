"""Tasks by name: `opt2skill generate <task>` and every other tool look tasks up here."""

from __future__ import annotations

from typing import Any

from opt2skill.errors import ConfigError
from opt2skill.model.robot import Robot
from opt2skill.trajopt.task import Task


def _tasks() -> dict[str, type[Task]]:
    from opt2skill.baselines.ik_walk import IKWalkTask
    from opt2skill.trajopt.squat import SquatTask
    from opt2skill.trajopt.walk import WalkTask

    tasks: dict[str, type[Task]] = {task.name: task for task in (SquatTask, WalkTask, IKWalkTask)}
    return tasks


def available_tasks() -> list[str]:
    return sorted(_tasks())


def task_class(name: str) -> type[Task]:
    tasks = _tasks()
    if name not in tasks:
        raise ConfigError(f"unknown task '{name}'; tasks: {', '.join(sorted(tasks))}")
    return tasks[name]


def get_task(name: str, robot: Robot, overrides: dict[str, Any] | None = None) -> Task:
    """The task `name` for `robot`, its config defaults replaced by `overrides` (checked)."""
    return task_class(name)(robot, overrides)
