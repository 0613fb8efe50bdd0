"""State and control regularization (Eq. 2's R term and the posture part of Q), one config section."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from opt2skill.model.robot import Robot
from opt2skill.trajopt.config import require


@dataclass(frozen=True)
class Posture:
    """Per-part weights of the state residual x (-) x_ref, and of torques scaled by their limits."""

    base_position: float = 0.0
    base_orientation: float = 10.0
    legs: float = 0.3
    arms: float = 3.0
    base_velocity: float = 1.0
    leg_velocity: float = 0.3
    arm_velocity: float = 1.0
    state_weight: float = 10.0
    control_weight: float = 1.0  # on (u / torque limit)
    terminal_weight: float = 100.0  # the terminal node's state term is this many times heavier

    def check(self) -> None:
        values = (self.state_weight, self.control_weight, self.terminal_weight)
        require(all(v >= 0 for v in values), "posture weights must be >= 0")

    def weights(self, robot: Robot) -> np.ndarray:
        """Weights over the state tangent (2 nv): base position, orientation, joints, velocities."""
        nv = robot.nv
        cfg = robot.config
        legs = np.concatenate([cfg.group_indices(g) for g in cfg.joint_groups if g.endswith("_leg")])
        w = np.zeros(2 * nv)
        w[0:3] = self.base_position
        w[3:6] = self.base_orientation
        w[6:nv] = self.arms
        w[6 + legs] = self.legs
        w[nv : nv + 6] = self.base_velocity
        w[nv + 6 :] = self.arm_velocity
        w[nv + 6 + legs] = self.leg_velocity
        return w

    def terms(self, terms, x_ref: np.ndarray, weights: np.ndarray, kind: str) -> list:
        """State (and, on running nodes, control) regularization for one node."""
        scale = self.terminal_weight if kind == "terminal" else 1.0
        out = [("posture", terms.state_reg(x_ref, weights), self.state_weight * scale)]
        if kind == "running" and self.control_weight > 0:
            limits = terms.robot.config.torque_limit
            out.append(("torque", terms.control_reg(1.0 / limits), self.control_weight))
        return out
