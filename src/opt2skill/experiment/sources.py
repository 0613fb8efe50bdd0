"""The three reference datasets of Table III with matched ranges: TO walks (`generate walk`), IK walks
of the same parameters (`generate walk_ik`) and human walking retargeted to the robot (`retarget`).
Training references use the experiment's seed, held-out ones seed + 1 (other motions)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from opt2skill.experiment.settings import SOURCE_TASKS, ExperimentSettings
from opt2skill.experiment.steps import Unavailable

DEFAULT_WALK_DURATION = 14.0  # s, the walk task's own: a dataset made by plain `generate walk` is reused as is
CLIP_SUFFIXES = (".npz", ".bvh")


def dataset_dir(out: Path, source: str, split: str) -> Path:
    return Path(out) / "data" / f"{source}_{split}"


def build(source: str, split: str, s: ExperimentSettings, out: Path, progress: bool = True) -> dict[str, Any]:
    """Generate (or resume) one dataset; its counts. No accepted reference is `Unavailable`."""
    n, seed = (s.n_train, s.seed) if split == "train" else (s.n_test, s.seed + 1)
    folder = dataset_dir(out, source, split)
    if source == "human":
        summary = _human(s, out, split, n, seed, folder, progress)
    else:
        from opt2skill.trajopt.generate import GenerateRequest, generate

        config = {} if s.duration == DEFAULT_WALK_DURATION else {"duration": s.duration}
        summary = generate(GenerateRequest(task=SOURCE_TASKS[source], n=n, seed=seed, out=folder, workers=s.workers,
                                           ranges={"speed": s.speed, "clearance": s.clearance}, task_config=config,
                                           command="opt2skill experiment table3"), progress=progress)
    return dataset_result(summary, folder, f"{source} {split}")


def dataset_result(summary: dict[str, Any], folder: Path, what: str) -> dict[str, Any]:
    """A data step's result from its dataset's summary; no accepted reference is `Unavailable`."""
    counts = summary["counts"]
    result = {"dataset": str(folder), "requested": summary["requested"], "counts": counts,
              "reasons": summary.get("reasons", {}), "solve_time": summary.get("solve_time", {})}
    if not counts.get("accepted"):
        raise Unavailable(f"{what}: none of {summary['requested']} references accepted "
                          f"(reasons: {summary.get('reasons') or 'failed'}); see {folder}")
    return result


def _human(s: ExperimentSettings, out: Path, split: str, n: int, seed: int, folder: Path, progress: bool) -> dict:
    from opt2skill.cli.console import console
    from opt2skill.retarget.batch import retarget_files

    files = human_files(s, out, split, n, seed)
    if not files:
        raise Unavailable(f"human {split}: no clips (--human {s.human} has {len(human_files(s, out, 'all', 0, 0))} "
                          f"files; {s.n_test} are held out, the rest train)")
    return retarget_files(files, folder, command="opt2skill experiment table3", progress=progress,
                          log=lambda line: console.print(f"  {line}", highlight=False, soft_wrap=True))


def human_files(s: ExperimentSettings, out: Path, split: str, n: int, seed: int) -> list[Path]:
    """The clips of a split: the user's folder (sorted; the last `n_test` held out), or constructed
    clips drawn in the matched ranges (`retarget.synthetic`)."""
    if s.human is not None:
        files = sorted(p for p in Path(s.human).iterdir() if p.suffix.lower() in CLIP_SUFFIXES)
        if split == "all":
            return files
        cut = max(len(files) - s.n_test, 0)
        return files[:cut][:n] if split == "train" else files[cut:]
    from opt2skill.model import load_robot
    from opt2skill.retarget.pipeline import robot_leg_length
    from opt2skill.retarget.synthetic import HIP_HEIGHT, write_walking_clips

    ratio = robot_leg_length(load_robot("digit")) / HIP_HEIGHT
    return write_walking_clips(Path(out) / "human_clips" / split, n, seed, s.speed, s.clearance, s.human_duration, ratio)
