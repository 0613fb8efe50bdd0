"""Walking's task checks: realized against requested speed and foot clearance (for validation)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from opt2skill.data.record import FRAME_DT, Trajectory

if TYPE_CHECKING:
    from opt2skill.trajopt.walk import WalkTask


def walk_errors(task: WalkTask, traj: Trajectory) -> dict[str, dict[str, Any]]:
    th = task.config.thresholds
    gait, _ = task.gait(traj.params)
    first, last = gait.steps[0].liftoff, gait.steps[-1].touchdown
    frames = slice(int(round(first / FRAME_DT)), int(round(last / FRAME_DT)))
    # Mean velocity over the walk in the heading frame: realized (base) against commanded (plan).
    heading = gait.heading[frames]
    c, s = np.cos(heading), np.sin(heading)
    realized_w = traj.qvel[frames, :2]
    planned_w = gait.velocity[frames, :2]

    def in_heading(v: np.ndarray) -> np.ndarray:
        return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1]], 1).mean(0)

    speed_error = float(np.linalg.norm(in_heading(realized_w) - in_heading(planned_w)))
    ee = list(traj.ee_names)
    apex_errors = []
    for step in gait.steps:
        window = slice(int(round(step.liftoff / FRAME_DT)), int(round(step.touchdown / FRAME_DT)) + 1)
        z = traj.ee_pos[window, ee.index(step.swing), 2]
        ground = max(step.origin.position[2], step.target.position[2])
        apex_errors.append(abs(float(z.max()) - ground - traj.params["clearance"]))
    return {
        "speed_error": {"value": speed_error, "limit": th.speed_error, "unit": "m/s"},
        "clearance_error": {"value": float(np.median(apex_errors)), "limit": th.clearance_error, "unit": "m"},
    }
