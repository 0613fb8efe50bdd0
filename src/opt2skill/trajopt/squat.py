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
from opt2skill.trajopt.config import require
from opt2skill.trajopt.phase_task import PhaseTask, Plan
from opt2skill.trajopt.task_params import TASK_PARAMS
from opt2skill.trajopt.phases import Contact, Knot, Phase
from opt2skill.trajopt.posture import Posture
from opt2skill.trajopt.settings import ContactSettings, FeasibilityWeights, SolverSettings

PARAMS = TASK_PARAMS["squat"]


@dataclass(frozen=True)
class SquatThresholds:
    depth_error: float = 0.01  # m, |realized - requested| lowest CoM
    end_error: float = 0.01  # m, CoM back at its start height


@dataclass(frozen=True)
class SquatConfig:
    duration: float = 1.6  # s, a multiple of solver.dt
    com_weight: float = 1e5
    posture: Posture = field(default_factory=Posture)
    contact: ContactSettings = field(default_factory=ContactSettings)
    feasibility: FeasibilityWeights = field(default_factory=FeasibilityWeights)
    solver: SolverSettings = field(default_factory=lambda: SolverSettings(dt=0.02, max_iter=100))
    thresholds: SquatThresholds = field(default_factory=SquatThresholds)
    ranges: dict = field(default_factory=dict)  # parameter -> (low, high) sampling range

    def check(self) -> None:
        require(0.2 <= self.duration <= 10.0, f"duration = {self.duration:g} s must be in [0.2, 10] s")
        require(self.com_weight >= 0, "com_weight must be >= 0")
        for section in (self.posture, self.contact, self.feasibility, self.solver):
            section.check()


class SquatTask(PhaseTask):
    name = "squat"
    config_class = SquatConfig
    params = PARAMS

    def plan(self, params: dict[str, float]) -> Plan:
        cfg = self.config
        x0 = np.concatenate([self.robot.stand_q_pin, np.zeros(self.robot.nv)])
        pm = self.robot.pin_model
        data = pm.createData()
        q0 = x0[: pm.nq]
        pin.framesForwardKinematics(pm, data, q0)
        com0 = pin.centerOfMass(pm, data, q0).copy()
        feet = tuple(
            Contact(foot, data.oMf[self.builder.frame_id(foot)].copy())
            for foot in (f.name for f in self.robot.config.feet)
        )
        depth, period = params["depth"], cfg.duration
        posture = cfg.posture.weights(self.robot)

        def costs(knot: Knot, terms):
            s = knot.time / period
            # sin^4: down and back up with zero velocity and acceleration at both ends
            target = com0 - np.array([0.0, 0.0, depth * np.sin(np.pi * s) ** 4])
            out = [("com", terms.com(target), cfg.com_weight)]
            out += cfg.posture.terms(terms, x0, posture, knot.kind)
            return out

        return Plan(phases=[Phase(period, feet, costs, "squat")], x0=x0)

    def task_errors(self, traj: Trajectory) -> dict[str, dict[str, Any]]:
        th = self.config.thresholds
        z = traj.com[:, 2]
        depth = float(z[0] - z.min())
        return {
            "depth_error": {"value": abs(depth - traj.params["depth"]), "limit": th.depth_error, "unit": "m"},
            "end_error": {"value": float(abs(z[-1] - z[0])), "limit": th.end_error, "unit": "m"},
        }
