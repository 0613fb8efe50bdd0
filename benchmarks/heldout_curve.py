"""The robust time-to-skill curve of training runs, from their held-out judgements (issue 13).

A run trained with `opt2skill train ... --held-out DATA` judges its actor every `--judge-every`
iterations on held-out references of another seed under Table II's full randomization and
observation noise (`rl.best`, RUN/heldout.jsonl). This prints those judgements against training
wall-clock time, beside the paper's Table III row and the issue's success target, and plots success
and the four Table III errors of every run given:

    .venv/bin/python benchmarks/heldout_curve.py runs/a runs/b [--out bench/heldout_curve.png]

Runs that shared the machine say so in their names: wall-clock is each run's own training time.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from opt2skill.rl.best import JUDGEMENTS, TABLE_III, score
from opt2skill.rl.best import TABLE_III_UNITS as UNITS
MIN_SUCCESS = 0.95


def read(run: Path) -> list[dict]:
    path = Path(run) / JUDGEMENTS
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []


def table(run: Path, judgements: list[dict]) -> str:
    head = "| stage | iteration | training min | env steps | success | frames tracked | " + " | ".join(
        f"{k} {UNITS[k]}" for k in TABLE_III) + " |"
    lines = [f"**{run}** (held-out, Table II + noise)", "", head, "|" + " --- |" * (6 + len(TABLE_III)),
             "| Table III, Opt2Skill | | | | (>= 95 %) | | " + " | ".join(f"{v:g}" for v in TABLE_III.values()) + " |"]
    best = max(judgements, key=score) if judgements else None
    for j in judgements:
        errors = " | ".join("-" if j.get(k) is None else f"{j[k]:.3g}" for k in TABLE_III)
        mark = " (best)" if j is best else ""
        lines.append(f"| {j['stage']}{mark} | {j['iteration']} | {j.get('elapsed', 0) / 60:.1f} | {j['env_steps']:,} | "
                     f"{j['success']:.0%} | {j['tracked']:.0%} | {errors} |")
    return "\n".join(lines)


def plot(runs: list[tuple[Path, list[dict]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 1 + len(TABLE_III), figsize=(4 * (1 + len(TABLE_III)), 3.4))
    for run, judgements in runs:
        minutes = [j.get("elapsed", 0) / 60 for j in judgements]
        axes[0].plot(minutes, [100 * j["success"] for j in judgements], marker="o", label=Path(run).name)
        for ax, key in zip(axes[1:], TABLE_III):
            ax.plot(minutes, [j.get(key) if j.get(key) is not None else float("nan") for j in judgements], marker="o")
    axes[0].axhline(100 * MIN_SUCCESS, color="k", ls="--", lw=0.8)
    axes[0].set_ylabel("success % (Table II + noise)")
    axes[0].legend(fontsize=7)
    for ax, (key, target) in zip(axes[1:], TABLE_III.items()):
        ax.axhline(target, color="k", ls="--", lw=0.8)
        ax.set_ylabel(f"{key} ({UNITS[key]})")
        ax.set_yscale("log")
    for ax in axes:
        ax.set_xlabel("training wall-clock (min)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, nargs="*", help="run directories trained with --held-out")
    parser.add_argument("--out", type=Path, default=Path("bench/heldout_curve.png"))
    args = parser.parse_args()
    if not args.runs:  # `make bench` runs every benchmark without arguments
        print("heldout_curve: skipped, needs run directories trained with --held-out")
        return
    runs = [(run, read(run)) for run in args.runs]
    for run, judgements in runs:
        print(table(run, judgements) + "\n")
    plot(runs, args.out)
    print(f"plot: {args.out}")


if __name__ == "__main__":
    main()
