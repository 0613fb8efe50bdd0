"""Training beside a busy core: PPO iterations alone and with one core kept busy by another process,
under OpenMP spin settings, in one run.

Each case is `opt2skill train` for a few iterations (128 worlds, bf16 updates, every core) on a
dataset, from scratch, with GOMP_SPINCOUNT (or OMP_WAIT_POLICY) set as named; "busy" starts a
pure-Python loop beside it for the case's length. Prints the medians of the iteration time, the
collection's environment steps/s and the learner's samples/s (the first two iterations left out).

    .venv/bin/python benchmarks/shared_cores.py --dataset DIR [--iterations 15]
        [--settings command libgomp=300000 passive=PASSIVE]

`command` is what `opt2skill` sets by itself (opt2skill.cli.SPINCOUNT); `libgomp=300000` libgomp's
own default. docs/training.md ("Sharing the cores") has the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from sim_ceiling import machine

from opt2skill.cli import SPINCOUNT

CLI = str(Path(sys.executable).with_name("opt2skill"))
SETTINGS = {"command": {"GOMP_SPINCOUNT": SPINCOUNT}, "libgomp": {"GOMP_SPINCOUNT": "300000"},
            "passive": {"OMP_WAIT_POLICY": "PASSIVE"}}


def case(dataset: str, iterations: int, env: dict[str, str], busy: bool) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        full = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")} | env
        hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
        try:
            subprocess.run([CLI, "train", "--dataset", dataset, "--out", f"{tmp}/run", "--steps",
                            str(iterations * 128 * 48), "--num-envs", "128", "--mixed-precision", "--quiet"],
                           env=full, check=True, capture_output=True, text=True)
        finally:
            if hog is not None:
                hog.kill()
        rows = [json.loads(line) for line in open(f"{tmp}/run/progress.jsonl")][2:]
    return {key: statistics.median(r[f"perf/{key}"] for r in rows)
            for key in ("iteration_s", "env_steps_per_s", "learner_samples_per_s")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True, help="reference dataset to train on (a walk dataset)")
    parser.add_argument("--iterations", type=int, default=15, help="PPO iterations per case")
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), help=f"of {list(SETTINGS)}")
    args = parser.parse_args()
    print(machine())
    for name in args.settings:
        for busy in (False, True):
            r = case(args.dataset, args.iterations, SETTINGS[name], busy)
            print(f"{name:>8} {'busy core' if busy else 'alone':>9}: iteration {r['iteration_s']:.2f} s, collection "
                  f"{r['env_steps_per_s']:.0f} steps/s, learner {r['learner_samples_per_s']:.0f} samples/s", flush=True)


if __name__ == "__main__":
    main()
