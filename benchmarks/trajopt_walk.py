"""Walking trajectory optimization on one core: seconds per 14-s trajectory, iterations, acceptance.

A fixed, seeded set of walks over the full default parameter ranges is solved one after another in
this process (OMP_NUM_THREADS=1) and validated with `opt2skill.data.validate`. Printed: median and
p90 seconds per trajectory for the solve (plan + optimization + 200 Hz frames) and the validation
separately and together (wall and CPU seconds: on a shared machine the CPU time of this process is
the better figure), iterations, acceptance with the rejection reasons, peak memory, the load
average, and the cost of a cold full-horizon solve next to the default warm-started receding-window
solve.

Targets: issue 3, median <= 15 s per 14-s trajectory per core including validation, >= 90 %
accepted over the full parameter ranges; issue 19, median <= 5 s and >= 95 % accepted (at the target
on 2026-12-07: 4.97, 5.18 and 4.76 s in three runs, then 4.8 % off and 5.88 and 5.23 s on the VM's slower evening,
then 11.5 % off and 4.74 s at 23:38 UTC; docs/trajopt.md says what limits it). `--set key=value` (repeatable) solves with other settings, e.g.
a lever against the defaults on the same walks (docs/trajopt.md, "Speed", has the levers measured):

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/trajopt_walk.py --n 20 --seed 0
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/trajopt_walk.py --n 20 --seed 0 --set receding.max_iter=10

`--against-python` solves every walk with the compiled matched integrator and with its Python model,
in alternating order, and reports both (docs/trajopt.md, "Speed: the compiled matched integrator").
`--against-crocoddyl-barriers` does the same for the compiled barrier cost against Crocoddyl's
residual cost (the same walks to round-off; docs/trajopt.md, "Speed: barrier costs without their zeros").
`--against key=value` (repeatable) does the same for config overrides: each walk is solved with and
without them, in alternating order, and the per-walk ratio of the final costs is printed. On a
machine whose speed drifts, only such interleaved runs compare (docs/trajopt.md, "Speed: the
solver's own levers"):

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/trajopt_walk.py --n 20 --against solver.reg_increase_below=0.2

`--library-bound N` solves walks 0..N-1 again with their own solution as every node's guess (the
perfect library): the most a warm start from a library of solved walks could save (issue 19; 3.7 %
of the iterations and 2 % of the solver's seconds in the median of 5 walks, docs/trajopt.md).

`--against-python-replay` solves each walk once and validates it with the compiled feedback replay
and with the Python one, in alternating order. `--against-own-datas` solves every walk with the
matched nodes of one structure sharing one differential data (the default) and with a data per node
(the same walks to the bit; docs/trajopt.md, "The node loop is memory-bound"). `--against-python-frames`
solves every walk with the 200 Hz frames' tracking loop compiled and in Python (the same frames to
round-off; docs/trajopt.md, "Speed: the frames' tracking loop compiled"). `--against-crocoddyl-solver`
solves every walk with Box-FDDP's backward pass and the contact dynamics' derivatives compiled for
AVX2/FMA and with Crocoddyl's (the same plans to round-off; docs/trajopt.md, "Speed: the backward
pass and the contact dynamics' derivatives compiled for AVX2 and FMA").
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import resource
import time
from collections import Counter

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from opt2skill.data import replay  # noqa: E402
from opt2skill.data.validate import ValidationConfig, validate  # noqa: E402
from opt2skill.errors import SolverError  # noqa: E402
from opt2skill.model import load_robot  # noqa: E402
from opt2skill.tasks import get_task  # noqa: E402
from opt2skill.trajopt import costs, frames, integrator, native, phases, solver  # noqa: E402
from opt2skill.trajopt.config import parse_value  # noqa: E402
from opt2skill.trajopt.skills import locomotion  # noqa: E402


GAINS = {"solver.keep_gains": True}


def _stats(values: list[float]) -> str:
    if not values:
        return "n/a"
    return f"median {np.median(values):6.2f}  p90 {np.percentile(values, 90):6.2f}  max {max(values):6.2f}"


class _OwnSolution:
    """`extend` for the receding solve: node j's guess is a solved walk's own node j (state after it,
    control, gain), the guess a perfect library entry would give."""

    def __init__(self, solution):
        self.solution = solution

    def __call__(self, gx, gu, gK, j):
        return self.solution.xs[j + 1].copy(), np.array(self.solution.us[j]), np.array(self.solution.K[j])


def library_bound(robot, space, seed: int, n: int) -> None:
    """Walks 0..n-1 solved as by default (the stride guess) and again with their own solution as every
    node's guess: the iterations a warm start from a library of solved walks could save at most,
    before any neighbour's mismatch or retiming (issue 19; docs/trajopt.md)."""
    print(f"\nthe default stride guess against the perfect library (each walk's own solution as every node's "
          f"guess), walks 0 to {n - 1}")
    task = get_task("walk", robot, GAINS)
    solved = {}
    original_solve, original_guess = locomotion.solve_receding, locomotion.StrideGuess

    def keep(*args, **kwargs):
        solved["solution"] = original_solve(*args, **kwargs)
        return solved["solution"]

    rows = []
    for index in range(n):
        params = space.sample(seed, index)
        locomotion.solve_receding = keep
        try:
            stride = task.solve(params, seed)
            own = solved["solution"]
            locomotion.StrideGuess = lambda problem, gait: _OwnSolution(own)
            library = task.solve(params, seed)
        except SolverError as exc:
            print(f"  {index:3d} failed: {exc}")
            continue
        finally:
            locomotion.solve_receding, locomotion.StrideGuess = original_solve, original_guess
        a, b = stride.solver, library.solver
        rows.append((a["iterations"], b["iterations"], a["solve_time"], b["solve_time"]))
        print(f"  {index:3d} stride guess: {a['iterations']:4d} iterations {a['solve_time']:5.2f} s cost {a['cost']:8.2f}"
              f"  | own solution: {b['iterations']:4d} iterations {b['solve_time']:5.2f} s cost {b['cost']:8.2f}")
    if rows:
        saved = [1.0 - lib / max(default, 1) for default, lib, _, _ in rows]
        print(f"  iterations saved by the perfect library: median {100 * np.median(saved):.1f} %  "
              f"(min {100 * min(saved):.1f}, max {100 * max(saved):.1f}); solver seconds "
              f"{np.median([r[2] for r in rows]):.2f} -> {np.median([r[3] for r in rows]):.2f} (median)")


def cold_against_warm(robot, params: dict, seed: int, max_iter: int) -> None:
    """One walk solved cold over the full horizon (from standing everywhere) and warm (default)."""
    print(f"\ncold full-horizon solve against the default warm-started receding solve ({params_text(params)})")
    for label, overrides in (
        ("cold, full horizon", {"receding.enabled": False, "solver.max_iter": max_iter}),
        ("warm, receding windows", {}),
    ):
        task = get_task("walk", robot, {**GAINS, **overrides})
        start, start_cpu = time.perf_counter(), time.process_time()
        try:
            traj = task.solve(params, seed)
        except SolverError as exc:
            print(f"  {label:24s} failed after {time.perf_counter() - start:6.1f} s: {exc}")
            continue
        s = traj.solver
        print(
            f"  {label:24s} {time.perf_counter() - start:7.1f} s (cpu {time.process_time() - start_cpu:6.1f})  "
            f"solver {s['solve_time']:7.1f} s  "
            f"iterations {s['iterations']:4d}  cost {s['cost']:10.2f}  stop: {s['stop_reason']}"
        )


def _override(item: str) -> tuple[str, object]:
    key, _, raw = item.partition("=")
    return key, parse_value(raw)


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def params_text(params: dict) -> str:
    keys = ("speed", "clearance", "step_duration", "double_support", "height_offset")
    return ", ".join(f"{k} {params[k]:.3g}" for k in keys)


_SOLVERS: list = []  # the Box-FDDP solvers made since the last walk began (their line-search counts)


def _recording_box_fddp(shooting):
    made = _BOX_FDDP(shooting)
    _SOLVERS.append(made)
    return made


_BOX_FDDP = solver.box_fddp
solver.box_fddp = _recording_box_fddp


def _line_search_counts() -> tuple[int, int, int, int]:
    """(trials, stopped, nodes evaluated, nodes left out) of the compiled solver's line searches on
    trajectories without gaps (zeros with Crocoddyl's solver, which stops no trial)."""
    counts = [0, 0, 0, 0]
    for made in _SOLVERS:
        if hasattr(made, "line_search_trials"):
            for i, name in enumerate(("trials", "stopped", "nodes", "nodes_skipped")):
                counts[i] += getattr(made, f"line_search_{name}")
    return tuple(counts)


class Tally:
    """Seconds, iterations and verdicts of the walks solved with one implementation."""

    def __init__(self):
        self.solve, self.valid, self.total, self.solve_cpu, self.valid_cpu, self.total_cpu = ([] for _ in range(6))
        self.iterations, self.costs, self.accepted, self.reasons = [], [], 0, Counter()
        self.cost_of: dict[int, float] = {}  # walk index -> final cost
        self.line_search = [0, 0, 0, 0]  # trials, stopped, nodes, nodes left out (`_line_search_counts`)

    def walk(self, robot, task, config, index: int, params: dict, seed: int, label: str) -> None:
        start, start_cpu = time.perf_counter(), time.process_time()
        _SOLVERS.clear()
        try:
            traj = task.solve(params, seed)
            self.line_search = [a + b for a, b in zip(self.line_search, _line_search_counts())]
        except SolverError as exc:
            self.reasons["solver_failed"] += 1
            print(f"{index:3d} {label} FAILED ({time.perf_counter() - start:.1f} s): {exc}  [{params_text(params)}]", flush=True)
            return None
        solved, solved_cpu = time.perf_counter() - start, time.process_time() - start_cpu
        self.check(robot, task, config, index, params, label, traj, solved, solved_cpu)
        return traj, solved, solved_cpu

    def check(self, robot, task, config, index: int, params: dict, label: str, traj, solved: float,
              solved_cpu: float) -> None:
        """Validate a solved walk and record both times."""
        start, start_cpu = time.perf_counter(), time.process_time()
        result = validate(robot, traj, config, task.task_errors(traj))
        checked, checked_cpu = time.perf_counter() - start, time.process_time() - start_cpu
        self.solve.append(solved)
        self.valid.append(checked)
        self.total.append(solved + checked)
        self.solve_cpu.append(solved_cpu)
        self.valid_cpu.append(checked_cpu)
        self.total_cpu.append(solved_cpu + checked_cpu)
        self.iterations.append(traj.solver["iterations"])
        self.costs.append(traj.solver["cost"])
        self.cost_of[index] = traj.solver["cost"]
        self.accepted += bool(result["accepted"])
        self.reasons.update(result["reasons"])
        verdict = "accepted" if result["accepted"] else "rejected: " + ", ".join(result["reasons"])
        print(
            f"{index:3d} {label} solve {solved:6.1f} s (cpu {solved_cpu:5.1f})  validate {checked:5.1f} s (cpu {checked_cpu:4.1f})  "
            f"iterations {traj.solver['iterations']:4d}  cost {traj.solver['cost']:8.1f}  {verdict}  [{params_text(params)}]",
            flush=True,
        )

    def report(self, n: int, label: str) -> None:
        print(f"\nseconds per 14-s walk, one core{', ' + label if label else ''} (load average now {_load()})")
        print(f"  solve      wall {_stats(self.solve)}   cpu {_stats(self.solve_cpu)}")
        print(f"  validation wall {_stats(self.valid)}   cpu {_stats(self.valid_cpu)}")
        print(f"  total      wall {_stats(self.total)}   cpu {_stats(self.total_cpu)}   (target: median <= 5 s)")
        print(f"iterations   {_stats([float(i) for i in self.iterations])}")
        print(f"final cost   {_stats(self.costs)}   (the assembled walk's; lower is a better plan)")
        print(f"accepted     {self.accepted}/{n} = {100.0 * self.accepted / max(n, 1):.0f} %   (target >= 95 %)")
        print(f"reasons      {dict(self.reasons) or '-'}")
        trials, stopped, nodes, skipped = self.line_search
        if trials:
            print(f"line search  {stopped} of {trials} trials without gaps stopped once they could not be accepted; "
                  f"{100.0 * skipped / (nodes + skipped):.0f} % of their node evaluations left out")


@contextlib.contextmanager
def own_datas():
    """Problems built inside give every matched node its own differential data (no shared scratch)."""
    original = phases.share_scratch
    phases.share_scratch = lambda *args: None
    try:
        yield
    finally:
        phases.share_scratch = original


@contextlib.contextmanager
def uncompiled(*modules):
    """Problems built (and walks validated) inside use the Python or Crocoddyl version of the compiled
    parts that these modules would use (`integrator`: the matched integrator, `costs`: the barrier
    costs, `replay`: the feedback replay's loop, `frames`: the 200 Hz frames' tracking loop, `solver`: the
    backward pass compiled for AVX2/FMA, `phases`: the contact dynamics' derivatives compiled likewise)."""
    originals = [(module, module.load_native) for module in modules]
    for module, _ in originals:
        module.load_native = lambda: None
    try:
        yield
    finally:
        for module, load in originals:
            module.load_native = load


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=20, help="number of walks")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cold-max-iter", type=int, default=200, help="iteration cap of the cold solve (0: skip it)")
    parser.add_argument("--against-python", action="store_true",
                        help="solve each walk with the compiled and with the Python matched integrator, in alternating order")
    parser.add_argument("--against-crocoddyl-barriers", action="store_true",
                        help="solve each walk with the compiled barrier cost and with Crocoddyl's, in alternating order")
    parser.add_argument("--against-python-replay", action="store_true",
                        help="validate each solved walk with the compiled feedback replay and with the Python one, "
                             "in alternating order (the solve once)")
    parser.add_argument("--against-own-datas", action="store_true",
                        help="solve each walk with the matched nodes sharing a scratch data per structure and with "
                             "a data per node, in alternating order")
    parser.add_argument("--against-python-frames", action="store_true",
                        help="solve each walk with the 200 Hz frames' tracking loop compiled and in Python, "
                             "in alternating order")
    parser.add_argument("--against-crocoddyl-solver", action="store_true",
                        help="solve each walk with the solver's parts compiled for AVX2/FMA (the backward pass, "
                             "the contact dynamics' derivatives) and with Crocoddyl's, in alternating order")
    parser.add_argument("--library-bound", type=int, default=0, metavar="N",
                        help="after the walks, solve walks 0..N-1 again from their own solution (the perfect "
                             "library) and print the iterations that saves at most (0: skip)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a walk config override (dotted key, number or true/false), repeatable")
    parser.add_argument("--against", action="append", default=[], metavar="KEY=VALUE",
                        help="solve each walk also with this override (repeatable), in alternating order")
    args = parser.parse_args()
    if args.library_bound < 0:
        parser.error(f"--library-bound must be >= 0 (0: skip), got {args.library_bound}")
    if sum(map(bool, (args.against, args.against_python, args.against_crocoddyl_barriers, args.against_python_replay,
                      args.against_own_datas, args.against_python_frames, args.against_crocoddyl_solver))) > 1:
        parser.error("--against, --against-python, --against-crocoddyl-barriers, --against-python-replay, "
                     "--against-own-datas, --against-python-frames and --against-crocoddyl-solver compare one thing "
                     "at a time: give one of them")

    robot = load_robot("digit")
    overrides = dict(_override(item) for item in args.set)
    task = get_task("walk", robot, {**GAINS, **overrides})  # as `opt2skill generate`: the gains feed the feedback replay
    space = task.param_space()
    config = ValidationConfig()
    print(f"walk benchmark: {args.n} walks, seed {args.seed}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}, {time.strftime('%Y-%m-%d %H:%M')}, "
          f"load average {_load()}" + (f", overrides {overrides}" if overrides else ""))
    for flag, asked in (("--against-python", args.against_python),
                        ("--against-crocoddyl-barriers", args.against_crocoddyl_barriers),
                        ("--against-python-replay", args.against_python_replay),
                        ("--against-own-datas", args.against_own_datas),
                        ("--against-python-frames", args.against_python_frames)):
        if asked and native.load() is None:
            parser.error(f"{flag} needs the compiled parts: {native.unavailable_reason()}")
    if args.against_crocoddyl_solver and native.load_simd() is None:
        parser.error(f"--against-crocoddyl-solver needs the AVX2/FMA parts: {native.simd_unavailable_reason()}")
    print(f"compiled parts (matched integrator, barrier costs): "
          + ("yes" if native.load() is not None else f"no ({native.unavailable_reason()})")
          + f"; solver parts: {solver.solver_implementation()}"
          + (f" ({native.simd_unavailable_reason()})" if native.load_simd() is None else ""))
    # (label, task, the context it is solved in) of each way a walk is solved
    variants = [("", task, uncompiled)]
    if args.against_python:
        variants = [("compiled", task, uncompiled), ("python", task, lambda: uncompiled(integrator))]
    if args.against_crocoddyl_barriers:
        variants = [("compiled barriers", task, uncompiled), ("crocoddyl barriers", task, lambda: uncompiled(costs))]
    if args.against_own_datas:
        variants = [("shared scratch", task, uncompiled), ("own datas", task, own_datas)]
    if args.against_python_frames:
        variants = [("compiled frames", task, uncompiled), ("python frames", task, lambda: uncompiled(frames))]
    if args.against_crocoddyl_solver:
        variants = [("avx2-fma solver parts", task, uncompiled),
                    ("crocoddyl's own", task, lambda: uncompiled(solver, phases))]
    if args.against:
        against = dict(_override(item) for item in args.against)
        variants = [("default", task, uncompiled),
                    ("against", get_task("walk", robot, {**GAINS, **overrides, **against}), uncompiled)]
        print(f"against: {against}")
    if args.against_python_replay:
        variants = [("compiled replay", task, uncompiled), ("python replay", task, lambda: uncompiled(replay))]
    tallies = {label: Tally() for label, _, _ in variants}
    for index in range(args.n):
        params = space.sample(args.seed, index)
        if args.against_python_replay:  # one solve, validated both ways
            (first, _, context_first), (second, _, context_second) = variants if index % 2 == 0 else variants[::-1]
            with context_first():
                solved = tallies[first].walk(robot, task, config, index, params, args.seed, first)
            if solved is not None:
                with context_second():
                    tallies[second].check(robot, task, config, index, params, second, *solved)
            continue
        order = variants if index % 2 == 0 else variants[::-1]  # neither always runs first
        for label, solver_task, context in order:
            with context():
                tallies[label].walk(robot, solver_task, config, index, params, args.seed, label)
    for label, tally in tallies.items():
        tally.report(args.n, label)
    if len(tallies) == 2:
        first, second = tallies.values()
        both = sorted(set(first.cost_of) & set(second.cost_of))
        ratios = [second.cost_of[i] / first.cost_of[i] for i in both]
        if ratios:
            print(f"final cost, {variants[1][0]} / {variants[0][0]}, per walk: median {np.median(ratios):.3f}  "
                  f"min {min(ratios):.3f}  max {max(ratios):.3f}  ({len(ratios)} walks solved both ways)")
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak memory  {peak_mb:.0f} MB (resident, this process)")
    if args.cold_max_iter > 0:
        cold_against_warm(robot, space.sample(args.seed, 0), args.seed, args.cold_max_iter)
    if args.library_bound > 0:
        library_bound(robot, space, args.seed, args.library_bound)


if __name__ == "__main__":
    main()
