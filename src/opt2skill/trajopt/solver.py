"""Box-FDDP on a phase problem: warm starts, an early stop when the cost stalls, and statistics.

FDDP spends most of a cold solve taking tiny steps on barrier penalties once the cost is within a
fraction of a percent of its final value (pitfalls.md), so besides Crocoddyl's own stopping
criterion the solve ends when the cost fell by less than `stall_tol` (relative) over the last
`stall_window` iterations while the trajectory is dynamically feasible (no gaps); and, where
`commit_tol` is set, a receding window's solve ends once a full step leaves the part it keeps in place.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import crocoddyl
import numpy as np

from opt2skill.errors import SolverError
from opt2skill.trajopt.native import load_simd as load_native  # the backward pass compiled for AVX2/FMA
from opt2skill.trajopt.phases import Problem
from opt2skill.trajopt.settings import SolverSettings


@dataclass
class Solution:
    xs: np.ndarray  # (N + 1, nx) states at the nodes, Pinocchio layout
    us: list[np.ndarray]  # per node (empty for impulse nodes)
    K: list[np.ndarray]  # feedback gains per node, (nu, ndx)
    cost: float
    iterations: int
    converged: bool  # Crocoddyl's criterion or the stall rule was met
    stop_reason: str
    seconds: float
    gap: float  # largest dynamic gap (defect) between nodes
    costs: list[float] = field(default_factory=list)  # cost after each iteration
    steps: list[float] = field(default_factory=list)  # accepted step length of each iteration
    regularization: list[float] = field(default_factory=list)  # Crocoddyl's preg after each iteration
    windows: list[tuple] = field(default_factory=list)  # receding solves: (start s, iterations, stop, seconds)

    def stats(self) -> dict:
        return {
            "cost": self.cost,
            "iterations": self.iterations,
            "converged": self.converged,
            "stop_reason": self.stop_reason,
            "solve_seconds": self.seconds,
            "gap": self.gap,
        }


class _Monitor(crocoddyl.CallbackAbstract):
    """Records the cost per iteration and ends the solve when it stalls (Crocoddyl checks th_stop
    right after the callbacks, and only once the trajectory is feasible)."""

    def __init__(self, settings: SolverSettings, committed: int | None = None):
        super().__init__()
        self.settings = settings
        self.costs: list[float] = []
        self.steps: list[float] = []
        self.regularization: list[float] = []  # after each iteration's update
        self.stalled = False
        self.settled = False  # the committed part stopped moving (`SolverSettings.commit_tol`)
        # the states of the nodes a receding window keeps (x0 excluded: fixed), watched when commit_tol > 0
        self.committed = committed if settings.commit_tol > 0 else None
        self._last: np.ndarray | None = None

    def __call__(self, solver):
        cost = float(solver.cost)
        self.costs.append(cost)
        self.steps.append(float(solver.stepLength))
        self.regularization.append(float(solver.preg))
        if self.committed and self._committed_settled(solver):
            self.settled = True
            solver.th_stop = np.inf
            return
        window = self.settings.stall_window
        if len(self.costs) > window:
            before = self.costs[-1 - window]
            small = self.settings.stall_tol * max(abs(cost), 1e-12)
            # Converged for our purposes: little progress lately, and little expected from a full step
            # (tiny steps far from the optimum have a large expected improvement: keep going).
            expected = float(solver.d[0] + 0.5 * solver.d[1])
            if before - cost <= small and expected <= 10.0 * small:
                self.stalled = True
                solver.th_stop = np.inf

    def _committed_settled(self, solver) -> bool:
        states = np.array(solver.xs[1 : self.committed + 1])
        last, self._last = self._last, states
        # a full step that barely moves them: a short step moves little far from the optimum too
        return (last is not None and solver.isFeasible and solver.stepLength >= 1.0
                and float(np.abs(states - last).max()) <= self.settings.commit_tol)


def solve(
    problem: Problem,
    settings: SolverSettings,
    init_xs: list[np.ndarray] | np.ndarray | None = None,
    init_us: list[np.ndarray] | None = None,
    max_iter: int | None = None,
) -> Solution:
    """Solve a phase problem from a guess (default: the initial state everywhere, quasi-static torques)."""
    return solve_shooting(problem.shooting, settings, init_xs, init_us, max_iter)


def box_fddp(shooting: crocoddyl.ShootingProblem) -> crocoddyl.SolverBoxFDDP:
    """Crocoddyl's Box-FDDP, its backward pass compiled for AVX2 and FMA where this CPU has them, and
    its line-search trials stopped once they cannot be accepted (`trajopt.native`; the same iterations,
    the same plans to round-off)."""
    compiled = load_native()
    return compiled.BoxFDDP(shooting) if compiled is not None else crocoddyl.SolverBoxFDDP(shooting)


def solver_implementation() -> str:
    """'avx2-fma' where this process solves with the parts compiled for AVX2 and FMA (Box-FDDP's backward
    pass here, the contact dynamics' derivatives in `phases.contact_dynamics`), else 'crocoddyl'."""
    return "avx2-fma" if load_native() is not None else "crocoddyl"


def riccati_gains(shooting: crocoddyl.ShootingProblem, xs, us, regularization: float) -> list[np.ndarray]:
    """The feedback gains of a solved motion: one Box-FDDP backward pass over the whole problem at
    (xs, us), its Quu and Vxx diagonals raised by `regularization` (Crocoddyl's preg). An impulse
    node keeps its empty gain; a control at a torque bound gets a zero row, as in the solve."""
    solver = box_fddp(shooting)
    solver.setCandidate([np.asarray(x, dtype=float) for x in xs], [np.asarray(u, dtype=float) for u in us], True)
    solver.preg = solver.dreg = float(regularization)
    solver.calcDiff()
    solver.backwardPass()
    return [np.array(k) for k in solver.K]


def solve_shooting(
    shooting: crocoddyl.ShootingProblem,
    settings: SolverSettings,
    init_xs: list[np.ndarray] | np.ndarray | None = None,
    init_us: list[np.ndarray] | None = None,
    max_iter: int | None = None,
    is_feasible: bool = False,
    committed: int | None = None,
) -> Solution:
    """Box-FDDP on a Crocoddyl problem; `is_feasible`: the guess is a rollout (no gaps); `committed`:
    how many nodes after x0 a receding window keeps (for `SolverSettings.commit_tol`)."""
    solver = box_fddp(shooting)
    solver.alphas = [2.0**-i for i in range(settings.line_search_steps)]
    solver.th_stepInc = settings.reg_increase_below
    solver.th_acceptStep = settings.accept_step
    solver.th_stop = settings.stop
    monitor = _Monitor(settings, committed)
    solver.setCallbacks([monitor])
    if init_xs is None:
        init_xs = [shooting.x0.copy() for _ in range(shooting.T + 1)]
    init_xs = [np.asarray(x, dtype=float) for x in init_xs]
    if init_us is None:
        init_us = list(shooting.quasiStatic(init_xs[:-1]))
    cap = max_iter or settings.max_iter
    start = time.perf_counter()
    try:
        done = solver.solve(init_xs, list(init_us), cap, is_feasible, settings.reg_init)
    except Exception as exc:  # Crocoddyl raises plain RuntimeErrors from C++
        raise SolverError(f"Box-FDDP failed: {str(exc).strip()[:200]}") from None
    seconds = time.perf_counter() - start
    xs = np.array(solver.xs)  # one copy (indexing solver.xs element-wise can outlive its buffer)
    if not np.all(np.isfinite(xs)) or not np.isfinite(solver.cost):
        raise SolverError("Box-FDDP diverged: the state or the cost is not finite")
    us = [np.array(u) for u in solver.us]
    K = [np.array(k) for k in solver.K]
    gap = max((float(np.abs(f).max()) for f in solver.fs if len(f)), default=0.0)
    if monitor.settled:
        reason = "settled"
    elif monitor.stalled:
        reason = "stall"
    elif done:
        reason = "converged"
    else:
        reason = "max_iter" if len(monitor.costs) >= cap else "regularization"
    return Solution(
        xs=xs,
        us=us,
        K=K,
        cost=float(solver.cost),
        iterations=len(monitor.costs),
        converged=bool(done),
        stop_reason=reason,
        seconds=seconds,
        gap=gap,
        costs=monitor.costs,
        steps=monitor.steps,
        regularization=monitor.regularization,
    )
