"""The desk-height transfer test of Sec. IV-F: references made for one desk top (the paper's 0.95 m,
15 N) tracked by a policy with the desk moved to another height (`Scene.with_prop`), the reference
motion unchanged. Measured per reference: the hands' mean normal force while the reference holds
its force (its plateau) and the right hand's position error (cm), as the paper reports them."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

from opt2skill.data.atomic import write_json
from opt2skill.eval.stats import mean_sd
from opt2skill.experiment.force_figure import hand_normal_force, save_profiles

DESK = "desk"  # the wiping scene's desk prop
PLATEAU = 0.9  # a frame holds the force when the reference presses with at least this share of its level


def track_moved_desk(run: Path, dataset: Path, n: int, desk_height: float, folder: Path,
                     threads: int | None = None) -> dict[str, Any]:
    """Track the first `n` references of `dataset` with the run's policy, the desk top at
    `desk_height`; the figures per reference and their mean ± SD, written to FOLDER/transfer.json."""
    from opt2skill.data.reader import Dataset
    from opt2skill.eval.evaluate import eval_config, load_run_policy
    from opt2skill.eval.rollout import rollout
    from opt2skill.eval.task_metrics import task_metrics

    policy = load_run_policy(Path(run))
    data = Dataset.open(dataset)
    positions = data.sound(range(min(n, len(data))))
    references = [data[p] for p in positions]
    moved = [dataclasses.replace(r, scene=r.scene.with_prop(DESK, height=desk_height)) for r in references]
    start = time.perf_counter()
    rollouts = rollout(policy.robot, moved, policy.policy, eval_config(policy.spec.tracking), threads=threads)
    per_reference = []
    for position, r in zip(positions, rollouts):
        n_frames = r.tracked.num_frames
        reference_force = hand_normal_force(r.reference, n_frames)
        level = float(r.reference.params["force"])
        held = reference_force >= PLATEAU * level if level > 0 else reference_force > 0
        tracked_force = hand_normal_force(r.tracked, n_frames)
        metrics = task_metrics(r.reference, r.tracked)
        per_reference.append({
            "index": data.meta(position).index, "params": r.reference.params, "fell": r.fell, "frames": n_frames,
            "reference_frames": r.reference.num_frames, "held_frames": int(held.sum()),
            "force": float(tracked_force[held].mean()) if held.any() else float("nan"),
            "reference_force": float(reference_force[held].mean()) if held.any() else float("nan"),
            "hand_error": metrics["right_hand_error"][0], "force_error": metrics["force_error"][0]})
    result = {"desk_height": desk_height, "reference_desk_height": [r.params["desk_height"] for r in references],
              "policy": policy.info["description"], "dataset": str(dataset), "references": per_reference,
              "elapsed_s": time.perf_counter() - start,
              **{f"{name}_mean_sd": mean_sd([p[name] for p in per_reference])
                 for name in ("force", "reference_force", "hand_error", "force_error")}}
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / "transfer.json", result)
    save_profiles(rollouts, folder / "profiles.npz")
    return result
