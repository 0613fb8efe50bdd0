"""How a walk is solved: receding windows warm-started by the gait's periodicity.

Inside the walk the node pattern repeats every stride (two steps), and a stride's motion is the
previous stride's moved along the planned path. So the guess for a node beyond what has been
solved is the node one stride earlier, its base pose carried by the planned displacement (rotation
about z and translation; Pinocchio's velocities are in the body frame and carry over unchanged).
Before the first full stride and after the last step the guess holds the last state, at rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from opt2skill.trajopt.config import require
from opt2skill.trajopt.skills.gait import GaitPlan
from opt2skill.trajopt.phases import Problem
from opt2skill.trajopt.receding import HoldGuess


@dataclass(frozen=True)
class RecedingSettings:
    enabled: bool = True  # False: one full-horizon solve (slow for long walks; cold-solve baseline)
    window: float = 1.4  # s per window
    commit: float = 0.7  # s kept from each window
    max_iter: int = 20  # per window
    first_max_iter: int = 60  # the first window starts cold
    retry_window: float = 2.0  # s: a walk whose solve fails is solved again with windows this long (0: no retry)

    def check(self) -> None:
        require(self.window > 0 and 0 < self.commit <= self.window, "receding: need 0 < commit <= window")
        require(self.max_iter >= 1 and self.first_max_iter >= 1, "receding: max_iter >= 1")
        require(self.retry_window == 0 or self.retry_window >= self.commit, "receding: retry_window must be 0 or >= commit")


class StrideGuess:
    """`extend` for `solve_receding`: the next node's guess from one stride before."""

    def __init__(self, problem: Problem, gait: GaitPlan):
        self.problem = problem
        self.gait = gait
        self.nodes = problem.nodes
        self.nq = problem.shooting.runningModels[0].state.nq
        self.nv = problem.shooting.runningModels[0].state.nv
        steps = gait.steps
        self.stride = steps[2].start - steps[0].start if len(steps) > 2 else None
        times = [n.time for n in self.nodes]
        if self.stride is not None:
            first = steps[0].liftoff
            i0 = int(np.searchsorted(times, first - 1e-9))
            i1 = int(np.searchsorted(times, first + self.stride - 1e-9))
            self.period = i1 - i0  # nodes per stride (running and impulse)
        self.hold = HoldGuess(problem)  # before the first full stride and after the last step

    def __call__(self, gx: list, gu: list, gK: list, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        node = self.nodes[j]
        src = j - self.period if self.stride is not None else -1
        periodic = (
            self.stride is not None
            and src >= 0
            and node.time >= self.gait.steps[0].liftoff + self.stride - 1e-9
            and node.time < self.gait.walk_end - 1e-9
            and self.nodes[src].kind == node.kind
        )
        if periodic:
            x = self._carry(gx[src + 1], self.nodes[src + 1].time, self.nodes[j + 1].time)
            return x, gu[src].copy(), gK[src].copy()
        return self.hold(gx, gu, gK, j)

    def _carry(self, x: np.ndarray, t_from: float, t_to: float) -> np.ndarray:
        """x with its base pose moved by the planned path's displacement from t_from to t_to."""
        c_a, psi_a, _ = self.gait.sample(t_from)
        c_b, psi_b, _ = self.gait.sample(t_to)
        dpsi = psi_b - psi_a
        R = np.array([[np.cos(dpsi), -np.sin(dpsi)], [np.sin(dpsi), np.cos(dpsi)]])
        out = x.copy()
        out[:2] = R @ (x[:2] - c_a) + c_b
        out[2] += self.gait.support_height(t_to) - self.gait.support_height(t_from)  # stairs: a stride climbs
        turn = pin.Quaternion(pin.utils.rpyToMatrix(0.0, 0.0, dpsi))
        out[3:7] = (turn * pin.Quaternion(x[3:7])).coeffs()  # x, y, z, w
        return out
