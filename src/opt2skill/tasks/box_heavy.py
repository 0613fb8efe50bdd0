"""Heavy box (paper Sec. IV-E, a 4.9-kg box): the shelf-to-shelf pickup with box masses 0 to 5 kg.

The plan is the box pickup's (`tasks.box_pickup`): the hands reach their grasp goals first, then
both follow the lift goals; the box's mass is carried as a payload split between the hands, and the
squeeze grows with it so friction holds the box. Only the sampled mass range differs.
"""

from __future__ import annotations

import dataclasses

from opt2skill.tasks import TaskInfo
from opt2skill.tasks.box_pickup import PARAMS as PICKUP_PARAMS
from opt2skill.tasks.box_pickup import BoxPickupTask

PARAMS = tuple(dataclasses.replace(p, default_range=(0.0, 5.0)) if p.name == "box_mass" else p for p in PICKUP_PARAMS)


class BoxHeavyTask(BoxPickupTask):
    name = "box_heavy"
    params = PARAMS


INFO = TaskInfo(
    name="box_heavy",
    summary="the shelf-to-shelf pickup with a box of 0 to 5 kg (the paper lifts 4.9 kg)",
    task=BoxHeavyTask,
    params=PARAMS,
    demo_ranges={"box_mass": (2.0, 3.0), "upward": (0.6, 1.0)},
)
