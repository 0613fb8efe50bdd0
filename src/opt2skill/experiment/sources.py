"""The three reference datasets of Table III with matched ranges: TO walks (`generate walk`), IK walks
of the same parameters (`generate walk_ik`) and human walking retargeted to the robot (`retarget`).
Training references use the experiment's seed, held-out ones seed + 1 (other motions).

`--n-train` and `--n-test` count accepted references. The sources lose different shares to
validation (measured at the full setting: TO 2 %, IK 16 %, the constructed human clips 35 %, mostly
joint speed), so a dataset is topped up with the next indices or clips until that many are
accepted, up to `TOP_UP_LIMIT` times the count tried; a user's human folder tops up only with
the clips it has. Indices and clips are deterministic, so a topped-up dataset is the same whatever
the steps it took.

A finished data step records its references (`contents`: each one's fingerprint and a checksum of
its joint positions). An experiment folder carried to another machine without its `data/` (the
datasets are the bulk of it) gets them generated again by `present`, and they must be the same
references, or the resumed training would mix two datasets.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from opt2skill.experiment.settings import SOURCE_TASKS, ExperimentSettings
from opt2skill.errors import DataError
from opt2skill.experiment.steps import DONE, Steps, Unavailable

CHECKSUM_RTOL = 1e-9  # a regenerated reference's joint-position checksum against the recorded one
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
    result["contents"] = contents(folder)
    return result


def present(step: str, source: str, split: str, s: ExperimentSettings, out: Path, steps: Steps,
            progress: bool = True) -> dict[str, Any]:
    """Finished data step `step`'s record, its dataset on disk: one that is gone (the folder was
    carried without `data/`) is generated again and checked against the recorded `contents`; a
    record made before they were recorded gets them from the dataset that is there."""
    record = steps.record(step)
    if record is None or record["status"] != DONE:
        return record
    result = record["result"]
    folder = Path(result["dataset"])
    held = _held(folder)
    if held is not None and "contents" not in result:
        steps.amend(step, {**result, "contents": contents(folder)})
        return steps.record(step)
    if held is not None and held >= len(result["contents"]):
        return record
    from opt2skill.cli.console import console

    # A regeneration stopped part way leaves a dataset with fewer references than the policies saw:
    # the same command resumes it (the generator skips what is there) and checks it like a new one.
    why = "is gone" if held is None else f"holds {held} of its {len(result['contents'])} references"
    console.print(f"{step}: its dataset {folder} {why}; generating it again (the same seed and indices)",
                  highlight=False, soft_wrap=True)
    rebuilt = build(source, split, s, out, progress)
    if "contents" in result:
        _check_same(result["contents"], rebuilt["contents"], folder)
    steps.amend(step, {**result, "contents": rebuilt["contents"],
                       "regenerated": result.get("regenerated", 0) + 1})
    return steps.record(step)


def _held(folder: Path) -> int | None:
    """Accepted references in the dataset at `folder`, None if there is none."""
    if not folder.is_dir():
        return None
    from opt2skill.data.reader import Dataset

    return len(Dataset.open(folder))


def contents(folder: Path) -> list[list]:
    """[fingerprint, checksum] of each accepted reference: its task and parameters, and the sum of
    the absolute values of its joint positions over every frame."""
    import numpy as np

    from opt2skill.data.reader import Dataset
    from opt2skill.eval.references import position_fingerprint

    dataset = Dataset.open(folder)
    return [[position_fingerprint(dataset, i), float(np.abs(dataset.frames(i, ["qpos"])["qpos"]).sum())]
            for i in range(len(dataset))]


def _check_same(recorded: list[list], rebuilt: list[list], folder: Path) -> None:
    """DataError unless the regenerated references are the recorded ones (checksums to `CHECKSUM_RTOL`)."""
    import math

    old, new = dict(map(tuple, recorded)), dict(map(tuple, rebuilt))
    missing, extra = sorted(set(old) - set(new)), sorted(set(new) - set(old))
    moved = [k for k in set(old) & set(new) if not math.isclose(old[k], new[k], rel_tol=CHECKSUM_RTOL)]
    if missing or extra or moved:
        raise DataError(f"{folder} was generated again but holds other references than the experiment trained on "
                        f"({len(missing)} missing, {len(extra)} new, {len(moved)} with other joint positions, of "
                        f"{len(old)}); this machine's solver, or this version's task defaults (the walk's changed on "
                        "2026-12-07: docs/trajopt.md), do not reproduce them: move its data/ here too, or "
                        "start the experiment in a new --out")


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
