"""Kill-and-resume soak: `generate` and `train` killed with SIGKILL at random moments, then resumed.

    python benchmarks/kill_resume_soak.py [--kills 20] [--train-kills 20] [--task squat] [--n 60]
                                          [--iterations 40] [--out DIR] [--seed 0]

1. An uninterrupted `generate TASK --n N` is the reference. Its wall time and that of the same
   command rerun on the finished folder (start-up and checks only) set the window in which kills
   are drawn: from half the start-up to the start-up plus two items' worth of work, so that most
   kills land in the middle of the work and some during start-up, and the work lasts for all of them.
2. The same command into another folder is started and killed (the whole process group, workers
   included) after a uniformly drawn time in that window, until `--kills` kills have landed, then
   run to the end. Every record must
   then equal the reference's (the same status, the same arrays, knots, parameters and validation
   figures: everything except timing fields and provenance), `validate` must recompute every figure
   equal, and no index may be missing.
3. `train` on the reference dataset for `--iterations` iterations (4 worlds, a checkpoint every
   iteration) is killed `--train-kills` times the same way, then run to the end. Its progress log
   must list iterations 1..N once each, and every checkpoint left must load.

It prints the counts: kills that landed, records compared, corrupt or lost records, progress-log
gaps and duplicates. Not a test: at full scale it takes about ten minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CLI = [sys.executable, "-m", "opt2skill"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
TIMING = {"solve_time", "total_time", "time", "iteration_times", "window_times"}  # wall-clock fields, not content


def run(args: list[str], timeout: float | None = None) -> tuple[int | None, float]:
    """The command's exit status (None: killed at `timeout` s) and its wall time."""
    start = time.perf_counter()
    proc = subprocess.Popen([*CLI, *args], env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the driver and its workers, at once
        proc.communicate()
        return None, time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"{' '.join(args)} failed ({proc.returncode}): {err.decode()[-2000:]}")
    return proc.returncode, time.perf_counter() - start


def kill_window(full: float, startup: float, items: int) -> tuple[float, float]:
    """Kill times: from half the start-up to the start-up plus two items' worth of work (s)."""
    per_item = max(full - startup, 0.1) / items
    return 0.5 * startup, startup + 2 * per_item


def killed_then_finished(args: list[str], kills: int, window: tuple[float, float], rng) -> int:
    """Run `args` killed after a random time in `window` s until `kills` kills have landed (or until
    it finishes first), then to the end; the number of kills that landed."""
    landed = 0
    while landed < kills:
        code, _ = run(args, timeout=float(rng.uniform(*window)))
        if code is not None:
            return landed  # it finished before the kill: nothing left to interrupt
        landed += 1
    run(args)
    return landed


def _without_timing(value):
    if isinstance(value, dict):
        return {k: _without_timing(v) for k, v in value.items() if k not in TIMING}
    if isinstance(value, list):
        return [_without_timing(v) for v in value]
    return value


def same_record(a: Path, b: Path) -> bool:
    from opt2skill.data.record import FRAME_FIELDS
    from opt2skill.data.trajfile import read_trajectory

    ta, tb = read_trajectory(a), read_trajectory(b)
    arrays = all(np.array_equal(getattr(ta, f), getattr(tb, f)) for f in FRAME_FIELDS)
    knots = ta.knots.keys() == tb.knots.keys() and all(np.array_equal(ta.knots[k], tb.knots[k]) for k in ta.knots)
    return arrays and knots and ta.params == tb.params and \
        _without_timing(ta.validation) == _without_timing(tb.validation) and \
        _without_timing(ta.solver) == _without_timing(tb.solver)


def compare_datasets(reference: Path, resumed: Path) -> dict[str, int]:
    counts = {"records": 0, "corrupt": 0, "lost": 0, "extra": 0}
    for sub, suffix in (("trajectories", ".h5"), ("rejected", ".h5"), ("failed", ".json")):
        want = {p.name for p in (reference / sub).glob(f"*{suffix}")}
        have = {p.name for p in (resumed / sub).glob(f"*{suffix}")}
        counts["lost"] += len(want - have)
        counts["extra"] += len(have - want)
        for name in sorted(want & have):
            counts["records"] += 1
            if suffix == ".h5":
                try:
                    same = same_record(reference / sub / name, resumed / sub / name)
                except Exception:  # an unreadable record is a corrupt one
                    same = False
                counts["corrupt"] += not same
    return counts


def check_training(run_dir: Path, iterations: int) -> dict[str, int]:
    from opt2skill.rl import checkpoint
    from opt2skill.rl.run import read_progress

    logged = [r["iteration"] for r in read_progress(run_dir)]
    unreadable = 0
    for path in checkpoint.list_checkpoints(run_dir):
        try:
            checkpoint.load(path)
        except Exception:
            unreadable += 1
    return {"iterations logged": len(logged), "gaps": len(set(range(1, iterations + 1)) - set(logged)),
            "duplicates": len(logged) - len(set(logged)), "unreadable checkpoints": unreadable,
            "last checkpoint": checkpoint.list_checkpoints(run_dir)[-1].name}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kills", type=int, default=20, help="SIGKILLs of generate")
    parser.add_argument("--train-kills", type=int, default=20, help="SIGKILLs of train")
    parser.add_argument("--task", default="squat")
    parser.add_argument("--n", type=int, default=60, help="trajectories generated")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--iterations", type=int, default=40, help="PPO iterations of the soak run")
    parser.add_argument("--out", type=Path, default=None, help="work folder (default: a temporary one)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill times")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    root = args.out or Path(tempfile.mkdtemp(prefix="soak-"))
    gen = ["generate", args.task, "--n", str(args.n), "--workers", str(args.workers), "--keep-gains", "--quiet"]

    _, gen_time = run([*gen, "--out", str(root / "reference")])
    _, gen_startup = run([*gen, "--out", str(root / "reference")])  # finished: start-up and checks only
    gen_window = kill_window(gen_time, gen_startup, args.n / args.workers)
    gen_kills = killed_then_finished([*gen, "--out", str(root / "resumed")], args.kills, gen_window, rng)
    data = compare_datasets(root / "reference", root / "resumed")
    code, _ = run(["validate", str(root / "resumed"), "--workers", str(args.workers), "--quiet"])

    train = ["train", "--dataset", str(root / "reference"), "--num-envs", "4", "--threads", "1", "--quiet",
             "--checkpoint-every", "1", "--steps", str(args.iterations * 4 * 48)]
    _, train_time = run([*train, "--out", str(root / "run_reference")])
    _, train_startup = run([*train, "--out", str(root / "run_reference")])  # "already trained"
    train_window = kill_window(train_time, train_startup, args.iterations)
    train_kills = killed_then_finished([*train, "--out", str(root / "run")], args.train_kills, train_window, rng)
    training = check_training(root / "run", args.iterations)

    print(f"soak in {root} ({args.task}, --n {args.n}, {args.iterations} PPO iterations; uninterrupted runs "
          f"{gen_time:.1f} s and {train_time:.1f} s, start-up {gen_startup:.1f} s and {train_startup:.1f} s; kill times "
          f"uniform in [{gen_window[0]:.1f}, {gen_window[1]:.1f}] s and [{train_window[0]:.1f}, {train_window[1]:.1f}] s)")
    print(f"generate: {gen_kills} kills landed of {args.kills}; {data['records']} records compared; "
          f"{data['corrupt']} corrupt, {data['lost']} lost, {data['extra']} extra; validate exit status {code}")
    print(f"train: {train_kills} kills landed of {args.train_kills}; " + ", ".join(f"{k} {v}" for k, v in training.items()))


if __name__ == "__main__":
    main()
