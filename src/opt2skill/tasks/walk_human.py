"""Human walking retargeted to the robot (the paper's human-data baseline, Sec. IV-B).

Its references are not optimized or generated from parameters: `opt2skill retarget` makes them from
motion-capture clips (`opt2skill.retarget`, docs/baselines.md). This registration tells the rest of
the pipeline how to train and judge them: like the TO walk, without the base-position reward.
"""

from __future__ import annotations

from opt2skill.tasks import TaskInfo

INFO = TaskInfo(
    name="walk_human",
    summary="human walking clips retargeted to the robot (opt2skill retarget), no dynamics",
    task=None,
    params=(),
    track_base_position=False,
    made_by="opt2skill retarget",
)
