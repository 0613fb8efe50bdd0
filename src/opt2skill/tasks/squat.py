"""Squat: from the stand pose, lower the centre of mass by `depth` and come back, feet flat.

A small real task (one phase, both feet in 6D contact, about 1.6 s, about a second to solve) that
exercises the whole pipeline; dataset tooling tests use it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from opt2skill.data.record import Trajectory
from opt2skill.tasks import TaskInfo
from opt2skill.trajopt.config import require
from opt2skill.trajopt.params import Param
from opt2skill.trajopt.phase_task import PhaseTask, Plan
from opt2skill.trajopt.phases import Contact, Knot, Phase
from opt2skill.trajopt.settings import SolverSettings
from opt2skill.trajopt.task_config import TaskConfig

PARAMS = (
    Param("depth", allowed=(0.0, 0.2), default_range=(0.0, 0.15), unit="m", help="how far the CoM goes down"),
)


@dataclass(frozen=True)
class SquatThresholds:
    depth_error: float = 0.01  # m, |realized - requested| lowest CoM
    end_error: float = 0.01  # m, CoM back at its start height


@dataclass(frozen=True)
class SquatConfig(TaskConfig):
    duration: float = 1.6  # s, a multiple of solver.dt
    com_weight: float = 1e5
    thresholds: SquatThresholds = field(default_factory=SquatThresholds)
    solver: SolverSettings = field(default_factory=lambda: SolverSettings(dt=0.02, max_iter=100))

    def check_own(self) -> None:
        require(0.2 <= self.duration <= 10.0, f"duration = {self.duration:g} s must be in [0.2, 10] s")
        require(self.com_weight >= 0, "com_weight must be >= 0")


class SquatTask(PhaseTask):
    name = "squat"
    config_class = SquatConfig
    params = PARAMS

    def plan(self, params: dict[str, float]) -> Plan:
        cfg = self.config
        q0 = self.robot.stand_q_pin
        x0 = np.concatenate([q0, np.zeros(self.robot.nv)])
        pm = self.robot.pin_model
        data = pm.createData()
        pin.framesForwardKinematics(pm, data, q0)
        com0 = pin.centerOfMass(pm, data, q0).copy()
        feet = tuple(Contact(f.name, data.oMf[self.builder.frame_id(f.name)].copy()) for f in self.robot.config.feet)
        depth, period = params["depth"], cfg.duration

        def costs(knot: Knot, terms):
            s = knot.time / period
            # sin^4: down and back up with zero velocity and acceleration at both ends
            target = com0 - np.array([0.0, 0.0, depth * np.sin(np.pi * s) ** 4])
            return [("com", terms.com(target), cfg.com_weight)]

        return Plan(phases=[Phase(period, feet, costs, "squat")], x0=x0)

    def task_errors(self, traj: Trajectory) -> dict[str, dict[str, Any]]:
        th = self.config.thresholds
        z = traj.com[:, 2]
        depth = float(z[0] - z.min())
        return {
            "depth_error": {"value": abs(depth - traj.params["depth"]), "limit": th.depth_error, "unit": "m"},
            "end_error": {"value": float(abs(z[-1] - z[0])), "limit": th.end_error, "unit": "m"},
        }


INFO = TaskInfo(name="squat", summary="squat by a CoM depth and stand up (1.6 s)", task=SquatTask, params=PARAMS)
