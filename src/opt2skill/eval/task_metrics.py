"""A task's own metrics of one tracked motion (stair success, hand and placement errors, ...), as the
task registers them (`TaskInfo.metrics`), beside the paper's tracking errors; and, for every free
prop (a box) whose reference and tracked poses the records hold, its placement and whether it
was dropped."""

from __future__ import annotations

import numpy as np

from opt2skill.data.record import FRAME_DT, Trajectory

# m from the reference position at any frame: a dropped prop. The environment's default
# `TerminationConfig.max_prop_error` (not imported: the 2 kHz player's evaluation uses this module
# and imports nothing of the training code).
DROPPED = 0.15
# m from the reference's final position at the reference's end: a placed prop. The box tasks'
# validation limit for the expert (`placement_error`) and the 3 cm.
PLACED = 0.03


def task_metrics(reference: Trajectory, tracked: Trajectory) -> dict[str, tuple[float, str]]:
    """name -> (value, unit): the free props' metrics (`prop_metrics`), then the task's own (none
    when the reference's task registers none or is not known here)."""
    from opt2skill.tasks import available_tasks, task_info  # the task home loads the optimizer: only when asked

    out = prop_metrics(reference, tracked)
    if reference.task in available_tasks() and task_info(reference.task).metrics is not None:
        out.update(task_info(reference.task).metrics(reference, tracked))
    return out


def prop_metrics(reference: Trajectory, tracked: Trajectory) -> dict[str, tuple[float, str]]:
    """For each free prop with poses in both records: `NAME_placement_error`, the distance (m) from
    its position at the end of the tracked motion to the reference's final position (where the
    motion puts it down, however early the rollout ended), and `NAME_dropped`, 1 when it was ever
    more than `DROPPED` m from its reference position at the same frame (else 0; its mean is the
    drop rate), and `NAME_placed`, 1 when the motion ran to the reference's end and left the prop
    within `PLACED` m of where the reference puts it (its mean is the task's success rate)."""
    out = {}
    for name, pose in tracked.prop_poses.items():
        if name not in reference.prop_poses or not reference.scene.prop(name).free:  # a door has its task's metric
            continue
        ref = reference.prop_poses[name]
        n = min(len(pose), len(ref))
        out[f"{name}_placement_error"] = (float(np.linalg.norm(pose[-1, :3] - ref[-1, :3])), "m")
        apart = np.linalg.norm(pose[:n, :3] - ref[:n, :3], axis=1)
        out[f"{name}_dropped"] = (float(apart.max() > DROPPED), "")
        to_the_end = tracked.time[-1] >= reference.time[-1] - FRAME_DT / 2
        out[f"{name}_placed"] = (float(to_the_end and out[f"{name}_placement_error"][0] <= PLACED), "")
    return out
