"""Receding-window solves of a long phase problem: solve a window, keep its start, slide on.

A long motion (a 14-s walk has hundreds of nodes) is solved as overlapping windows of `window`
seconds. Each window starts from the state the previous one committed, is warm-started from the
previous window's solution where they overlap and from the task's `extend` guess beyond it, and
is capped at `max_iter` iterations; its first `commit` seconds are kept. One global step length
per FDDP iteration makes a full-horizon solve as slow as its hardest part; windows let each part
take its own steps. The assembled trajectory is dynamically feasible: every window starts from the
committed state, and a window whose solve stopped (iteration cap) before a full step closed its
gaps is replaced by the rollout of its own feedback law before it is committed. Each node carries
the feedback gains of the window that kept it.
"""

from __future__ import annotations

import time
from typing import Callable

import crocoddyl
import numpy as np

from opt2skill.errors import SolverError
from opt2skill.trajopt.integrator import compiled, single_threaded
from opt2skill.trajopt.phases import Problem
from opt2skill.trajopt.settings import SolverSettings
from opt2skill.trajopt.solver import Solution, solve_shooting

CLOSE_GAPS_ABOVE = 1e-9  # a window whose largest gap exceeds this is made feasible by rollout before committing

# (xs, us, Ks, j) -> guess of node j's next state, control and feedback gain from the nodes before it
Extend = Callable[[list, list, list, int], tuple[np.ndarray, np.ndarray, np.ndarray]]


class HoldGuess:
    """`extend` for `solve_receding`: the next node's guess holds the last state, at rest, with the
    torques that hold it there (quasi-static)."""

    def __init__(self, problem: Problem):
        self.problem = problem
        model = problem.shooting.runningModels[0]
        self.nq, self.nv = model.state.nq, model.state.nv

    def __call__(self, gx: list, gu: list, gK: list, j: int):
        x = gx[j].copy()
        x[self.nq :] = 0.0
        node = self.problem.nodes[j]
        if node.kind != "running":
            return x, np.zeros(0), np.zeros((0, 2 * self.nv))
        model, data = self.problem.shooting.runningModels[j], self.problem.shooting.runningDatas[j]
        return x, model.quasiStatic(data, gx[j]), np.zeros((model.nu, 2 * self.nv))



def solve_receding(
    problem: Problem,
    settings: SolverSettings,
    *,
    window: float,
    commit: float,
    max_iter: int,
    extend: Extend,
    first_max_iter: int | None = None,
) -> Solution:
    shooting = problem.shooting
    models = list(shooting.runningModels)
    datas = list(shooting.runningDatas)
    nodes = problem.nodes
    n = len(models)
    xs: list[np.ndarray] = [shooting.x0.copy()]
    us: list[np.ndarray] = []
    K: list[np.ndarray] = []
    guess_x: list[np.ndarray] = [shooting.x0.copy()]
    guess_u: list[np.ndarray] = []
    guess_K: list[np.ndarray] = []
    iterations, windows, costs, stops, per_window = 0, 0, [], [], []
    closed, open_gap = 0, 0.0
    start_time = time.perf_counter()
    s = 0
    while s < n:
        t_s = nodes[s].time
        e = _first_node_at(nodes, t_s + window, s + 1)
        c = n if e >= n else max(_first_node_at(nodes, t_s + commit, s + 1), s + 1)
        while len(guess_u) < e:
            x, u, k = extend(guess_x, guess_u, guess_K, len(guess_u))
            guess_x.append(x)
            guess_u.append(u)
            guess_K.append(k)
        terminal = problem.end_model(e) if e < n else shooting.terminalModel
        sub = _window(xs[s], models[s:e], terminal, datas[s:e])
        init_x, init_u, feasible = feedback_rollout(sub, guess_x[s : e + 1], guess_u[s:e], guess_K[s:e])
        cap = first_max_iter if (s == 0 and first_max_iter) else max_iter
        sol = solve_shooting(sub, settings, init_x, init_u, cap, is_feasible=feasible, committed=c - s)
        if sol.gap > CLOSE_GAPS_ABOVE:  # stopped before a full step closed its gaps: commit a rollout
            closed += 1
            open_gap = max(open_gap, sol.gap)
            sol.xs, sol.us = _close_gaps(sub, sol)
        iterations += sol.iterations
        windows += 1
        costs.append(sol.cost)
        stops.append(sol.stop_reason)
        per_window.append((round(t_s, 3), sol.iterations, sol.stop_reason, round(sol.seconds, 3)))
        keep = c - s
        xs.extend(sol.xs[1 : keep + 1])
        us.extend(sol.us[:keep])
        K.extend(sol.K[:keep])
        guess_x[s + 1 : e + 1] = list(sol.xs[1:])
        guess_u[s:e] = list(sol.us)
        guess_K[s:e] = list(sol.K)
        s = c
    seconds = time.perf_counter() - start_time
    xs_arr = np.array(xs)
    if not np.all(np.isfinite(xs_arr)):
        raise SolverError("receding-window solve diverged: a state is not finite")
    shooting_cost = shooting.calc(list(xs_arr), us)
    gap = _largest_gap(shooting, xs_arr)
    return Solution(
        xs=xs_arr,
        us=us,
        K=K,
        cost=float(shooting_cost),
        iterations=iterations,
        converged=all(stop in ("converged", "stall", "settled") for stop in stops),
        stop_reason=f"{windows} windows: " + ", ".join(sorted(set(stops)))
        + (f"; {closed} closed by rollout (largest gap {open_gap:.2g})" if closed else ""),
        seconds=seconds,
        gap=gap,
        costs=costs,
        windows=per_window,
    )


def feedback_rollout(shooting, xs_ref: list, us_ref: list, Ks: list, tolerance: float = 1.0) -> tuple[list, list, bool]:
    """A feasible guess where possible: roll the problem out from its x0 under u = u_ref - K (x_ref (-) x).

    The rollout stops where it leaves the reference by more than `tolerance` (state-tangent norm);
    from there on the guess is the reference itself (with gaps). Returns (xs, us, fully rolled out).
    """
    x = shooting.x0.copy()
    xs, us = [x], []
    rolled = True
    for j, (model, data) in enumerate(zip(shooting.runningModels, shooting.runningDatas)):
        u_ref, gain = us_ref[j], Ks[j]
        if not rolled:
            xs.append(xs_ref[j + 1].copy())
            us.append(u_ref.copy())
            continue
        if model.nu == 0:
            u = np.zeros(0)
        else:
            u = u_ref - gain @ model.state.diff(xs_ref[j], x) if gain.size else u_ref.copy()
            u = np.clip(u, model.u_lb, model.u_ub)
        model.calc(data, x, u)
        x = data.xnext.copy()
        if not np.all(np.isfinite(x)) or np.linalg.norm(model.state.diff(xs_ref[j + 1], x)) > tolerance:
            rolled = False
            x = xs_ref[j + 1].copy()
        xs.append(x)
        us.append(u)
    return xs, us, rolled


def _window(x0: np.ndarray, models: list, terminal, datas: list) -> crocoddyl.ShootingProblem:
    """A window's problem on the nodes' own datas: allocating a contact-dynamics node's data costs
    about 2.5 ms, 19 windows of about 50 nodes each. Python node models share their data instead
    (`integrator.MatchedEulerModel`), and Crocoddyl refuses it as a given data."""
    if all(compiled(m) for m in models):
        return single_threaded(crocoddyl.ShootingProblem(x0, models, terminal, datas, terminal.createData()))
    return crocoddyl.ShootingProblem(x0, models, terminal)


def _close_gaps(shooting, sol: Solution) -> tuple[np.ndarray, list]:
    """The window's solution made dynamically feasible: rolled out from its start under its own
    feedback law u = u_k - K_k (x_k (-) x), torques clipped to the box."""
    x = shooting.x0.copy()
    xs, us = [x], []
    for model, data, x_ref, u_ref, gain in zip(shooting.runningModels, shooting.runningDatas, sol.xs, sol.us, sol.K):
        u = np.clip(u_ref - gain @ model.state.diff(x_ref, x), model.u_lb, model.u_ub) if model.nu else np.zeros(0)
        model.calc(data, x, u)
        x = data.xnext.copy()
        if not np.all(np.isfinite(x)):
            raise SolverError("receding-window solve: closing a window's gaps by rollout diverged")
        xs.append(x)
        us.append(u)
    return np.array(xs), us


def _first_node_at(nodes, t: float, lower: int) -> int:
    """Index of the first running node at or after time t (or the number of running nodes)."""
    n = len(nodes) - 1  # the last node is the terminal one
    for i in range(lower, n):
        if nodes[i].time >= t - 1e-9 and nodes[i].kind == "running":
            return i
    return n


def _largest_gap(shooting, xs: np.ndarray) -> float:
    gap = 0.0
    for k, (model, data) in enumerate(zip(shooting.runningModels, shooting.runningDatas)):
        gap = max(gap, float(np.abs(model.state.diff(data.xnext, xs[k + 1])).max()))
    return gap


def solve_standing(problem: Problem, settings: SolverSettings, receding) -> Solution:
    """Receding windows for a task that stands (manipulation at a shelf or a desk): the nodes past a
    window's warm start begin as the last state held (`HoldGuess`). `receding`: the task's
    `RecedingSettings` (window, commit, max_iter, first_max_iter)."""
    return solve_receding(problem, settings, window=receding.window, commit=receding.commit,
                          max_iter=receding.max_iter, first_max_iter=receding.first_max_iter,
                          extend=HoldGuess(problem))
