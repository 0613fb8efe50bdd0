"""How a walking policy's gait departs from its references: pace, foot sweep, stance knee, height.

Rolls the policy out (deterministic actions, no randomization or noise: `eval`'s nominal world) on
every held-out walk of DATASET faster than --min-speed and prints, over those tracked to the end,
the medians and ranges of:

- pace: distance covered over the reference's (metrics.TrackingErrors.pace, x only here);
- foot sweep: the feet's fore-aft range in the base frame, reference and policy (a longer sweep at
  the reference's step timing is a longer step);
- stance knee: the knees' mean angle while the reference's foot is planted;
- base height.

    .venv/bin/python benchmarks/gait_pace.py experiments/table3-full/data/to_test RUN

RUN is a run directory or a shipped policy's name (`walk`). The first and last 2 s of each walk are
left out (start and stop). docs/experiments.md ("How the policies overshoot") has its figures.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from opt2skill import pretrained
from opt2skill.data.reader import Dataset
from opt2skill.eval.evaluate import eval_config, load_run_policy
from opt2skill.eval.rollout import rollout

EDGE = 400  # frames (2 s) left out at each end
FEET = ("left_foot", "right_foot")
PLANTED = 0.01  # m: a sole this close to the ground is planted


def gait(reference, tracked, knees: list[int]) -> dict[str, float]:
    n = tracked.num_frames
    span = slice(EDGE, n - EDGE)
    feet = [reference.ee_names.index(f) for f in FEET]

    def sweep(t) -> float:
        return float(np.mean([np.ptp(t.ee_pos_base[span, k, 0]) for k in feet]))

    def stance_knee(t) -> float:
        planted = [reference.ee_pos[span, k, 2] < PLANTED for k in feet]
        return float(np.mean([t.qpos[span, 7 + j][p].mean() for j, p in zip(knees, planted)]))

    distance = reference.qpos[n - 1, 0] - reference.qpos[0, 0]
    return {
        "speed (m/s)": reference.params["speed"],
        "pace": (tracked.qpos[-1, 0] - tracked.qpos[0, 0]) / distance,
        "foot sweep, reference (m)": sweep(reference), "foot sweep, policy (m)": sweep(tracked),
        "stance knee, reference (rad)": stance_knee(reference), "stance knee, policy (rad)": stance_knee(tracked),
        "base height, reference (m)": float(reference.qpos[span, 2].mean()),
        "base height, policy (m)": float(tracked.qpos[span, 2].mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("run", help="run directory, or a shipped policy's name")
    parser.add_argument("--min-speed", type=float, default=0.3, help="m/s; slower walks have too short a path")
    args = parser.parse_args()
    run_dir = Path(args.run) if Path(args.run).is_dir() else pretrained.pretrained_run(args.run)
    run = load_run_policy(run_dir)
    dataset = Dataset.open(args.dataset)
    references = [dataset[p] for p in range(len(dataset))]
    references = [r for r in references if r.params.get("speed", 0.0) > args.min_speed and r.num_frames > 3 * EDGE]
    knees = [run.robot.config.joint_names.index(name) for name in ("left_knee", "right_knee")]
    rollouts = rollout(run.robot, references, run.policy, eval_config(run.spec.tracking), threads=1)
    rows = [gait(r.reference, r.tracked, knees) for r in rollouts if not r.fell]
    print(f"{args.run} on {args.dataset}: {len(rows)} of {len(references)} walks faster than "
          f"{args.min_speed} m/s tracked to the end")
    for name in rows[0] if rows else ():
        values = np.array([row[name] for row in rows])
        print(f"  {name:30s} median {np.median(values):+.3f}   {values.min():+.3f} to {values.max():+.3f}")


if __name__ == "__main__":
    main()
