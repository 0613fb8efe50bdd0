"""The three reference datasets of Table III with matched ranges: TO walks (`generate walk`), IK walks
of the same parameters (`generate walk_ik`) and human walking retargeted to the robot (`retarget`).
Training references use the experiment's seed, held-out ones seed + 1 (other motions).

`--n-train` and `--n-test` count accepted references. The sources lose different shares to
validation (measured at the full setting: TO 2 %, IK 16 %, the constructed human clips 35 %, mostly
joint speed), so a dataset is topped up with the next indices or clips until that many are
accepted, up to `TOP_UP_LIMIT` times the count tried; a user's human folder tops up only with
the clips it has. Indices and clips are deterministic, so a topped-up dataset is the same whatever
the steps it took."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from opt2skill.experiment.settings import SOURCE_TASKS, ExperimentSettings
from opt2skill.experiment.steps import Unavailable

TOP_UP_LIMIT = 3  # at most this many references (or clips) tried per one wanted
DEFAULT_WALK_DURATION = 14.0  # s, the walk task's own: a dataset made by plain `generate walk` is reused as is
CLIP_SUFFIXES = (".npz", ".bvh")


def dataset_dir(out: Path, source: str, split: str) -> Path:
    return Path(out) / "data" / f"{source}_{split}"


def build(source: str, split: str, s: ExperimentSettings, out: Path, progress: bool = True) -> dict[str, Any]:
    """Generate (or resume) one dataset until it holds the wanted number of accepted references;
    its counts. No accepted reference is `Unavailable`."""
    wanted, seed = (s.n_train, s.seed) if split == "train" else (s.n_test, s.seed + 1)
    folder = dataset_dir(out, source, split)
    tried = wanted
    while True:
        summary, more = _make(source, split, s, out, tried, seed, folder, progress)
        accepted = summary["counts"].get("accepted", 0)
        tried = summary["requested"]
        if accepted >= wanted or not more or tried >= TOP_UP_LIMIT * wanted:
            break
        rate = max(accepted / tried, 1.0 / TOP_UP_LIMIT)  # the next batch's expected yield
        tried = min(TOP_UP_LIMIT * wanted, tried + math.ceil((wanted - accepted) / rate))
    result = dataset_result(summary, folder, f"{source} {split}")
    result["wanted"] = wanted
    return result


def _make(source: str, split: str, s: ExperimentSettings, out: Path, n: int, seed: int, folder: Path,
          progress: bool) -> tuple[dict[str, Any], bool]:
    """The dataset with `n` references tried (indices 0 .. n-1, or the first n clips), and whether
    more can be tried."""
    if source == "human":
        return _human(s, out, split, n, seed, folder, progress)
    from opt2skill.trajopt.generate import GenerateRequest, generate

    config = {} if s.duration == DEFAULT_WALK_DURATION else {"duration": s.duration}
    summary = generate(GenerateRequest(task=SOURCE_TASKS[source], n=n, seed=seed, out=folder, workers=s.workers,
                                       ranges={"speed": s.speed, "clearance": s.clearance}, task_config=config,
                                       command="opt2skill experiment table3"), progress=progress)
    return summary, True


def dataset_result(summary: dict[str, Any], folder: Path, what: str) -> dict[str, Any]:
    """A data step's result from its dataset's summary; no accepted reference is `Unavailable`."""
    counts = summary["counts"]
    result = {"dataset": str(folder), "requested": summary["requested"], "counts": counts,
              "reasons": summary.get("reasons", {}), "solve_time": summary.get("solve_time", {})}
    if not counts.get("accepted"):
        raise Unavailable(f"{what}: none of {summary['requested']} references accepted "
                          f"(reasons: {summary.get('reasons') or 'failed'}); see {folder}")
    return result


def _human(s: ExperimentSettings, out: Path, split: str, n: int, seed: int, folder: Path,
           progress: bool) -> tuple[dict[str, Any], bool]:
    from opt2skill.cli.console import console
    from opt2skill.retarget.batch import retarget_files

    n = max(n, _clips_in(folder))  # a rerun resumes a topped-up dataset with all its clips
    files = human_files(s, out, split, n, seed)
    if not files:
        raise Unavailable(f"human {split}: no clips (--human {s.human} has {len(human_files(s, out, 'all', 0, 0))} "
                          f"files; {s.n_test} are held out, the rest train)")
    summary = retarget_files(files, folder, command="opt2skill experiment table3", progress=progress,
                             log=lambda line: console.print(f"  {line}", highlight=False, soft_wrap=True))
    return summary, len(files) == n  # a user's folder can run out of clips


def _clips_in(folder: Path) -> int:
    """How many clips the dataset in `folder` was made from (0 if there is none yet)."""
    from opt2skill.data.store import HEADER, read_header

    return len(read_header(folder)["identity"].get("files", [])) if (folder / HEADER).is_file() else 0


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
