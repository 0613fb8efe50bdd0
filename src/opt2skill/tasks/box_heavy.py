"""Heavy box (paper Sec. IV-E, a 4.9-kg box): the shelf-to-shelf pickup with box masses 0 to 5 kg.

The plan is the box pickup's (`tasks.box_pickup`): the box's mass is carried as a payload split
between the hands, and the squeeze grows with it so friction holds the box; the arms' torques hold
that squeeze inside the solve (`trajopt.squeeze`), so the torque limits bind on it. Only the sampled
mass range differs (docs/trajopt.md, "Heavy box": 5 of 8 accepted, up to 4.74 kg).
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
