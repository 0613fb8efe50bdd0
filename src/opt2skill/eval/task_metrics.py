"""A task's own metrics of one tracked motion (stair success, hand and placement errors, ...), as the
task registers them (`TaskInfo.metrics`), beside the paper's tracking errors."""

from __future__ import annotations

from opt2skill.data.record import Trajectory


def task_metrics(reference: Trajectory, tracked: Trajectory) -> dict[str, tuple[float, str]]:
    """name -> (value, unit); none when the reference's task registers none or is not known here."""
    from opt2skill.tasks import available_tasks, task_info  # the task home loads the optimizer: only when asked

    if reference.task not in available_tasks() or task_info(reference.task).metrics is None:
        return {}
    return task_info(reference.task).metrics(reference, tracked)
