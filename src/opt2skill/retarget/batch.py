"""`opt2skill retarget FILE... --out DIR`: human clips to a dataset of Digit references, resumable.

Clip i is the i-th of the files given (sorted by path); the dataset's identity holds the file
names, so rerunning the same command skips the clips already done and another set of files into the
same directory is an error naming the difference, except a list that extends the dataset's: the
clips done keep their indices and the new ones follow (how `experiment table3` tops a source up).
Every file is read before any work: files that cannot be read are one `DataError` naming each
(nothing is written). A clip the robot cannot follow
is kept in `rejected/` with its reasons (the filters are validation figures). Every clip gets one
log line.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from opt2skill.data.atomic import write_json
from opt2skill.data.store import ACCEPTED, FAILED, HEADER, REJECTED, DatasetStore, Outcome, read_header
from opt2skill.data.summary import summarize
from opt2skill.data.validate import ValidationConfig, validate
from opt2skill.errors import ConfigError, DataError
from opt2skill.output_paths import check_output_dir
from opt2skill.provenance import provenance
from opt2skill.retarget.motion import HumanMotion
from opt2skill.retarget.pipeline import TASK, RetargetSettings, retarget


def read_motion(path: Path, fmt: str = "auto", up: str | None = None, unit: float | None = None) -> HumanMotion:
    """A clip by its format: BVH (`.bvh`) or AMASS-style SMPL(-H) (`.npz`)."""
    kind = fmt if fmt != "auto" else {".bvh": "bvh", ".npz": "smpl"}.get(path.suffix.lower(), "")
    if kind == "bvh":
        from opt2skill.retarget.bvh import read_bvh

        return read_bvh(path, unit=unit, up=up or "y")
    if kind == "smpl":
        from opt2skill.retarget.smpl import read_smpl

        return read_smpl(path, up=up or "z")
    raise ConfigError(f"{path}: unknown motion format (use a .bvh or .npz file, or --format bvh|smpl)")


def retarget_files(files: list[Path], out: Path, robot_name: str = "digit", fmt: str = "auto", up: str | None = None,
                   unit: float | None = None, command: str = "", progress: bool = True,
                   log: Callable[[str], None] = print) -> dict[str, Any]:
    """Retarget every file into the dataset `out`; returns its summary."""
    from opt2skill.model import load_robot

    if not files:
        raise ConfigError("retarget needs at least one motion file")
    missing = [str(f) for f in files if not Path(f).is_file()]
    if missing:
        raise ConfigError(f"motion files not found: {', '.join(missing)}")
    check_output_dir(out)
    files = sorted(Path(f) for f in files)
    motions, problems = [], []
    for f in files:
        try:
            motions.append(read_motion(f, fmt, up, unit))
        except (DataError, ConfigError) as exc:
            problems.append(str(exc))
    if problems:
        raise DataError(f"{len(problems)} of {len(files)} motion files cannot be read: " + "; ".join(problems))
    robot = load_robot(robot_name)
    settings, config = RetargetSettings(), ValidationConfig()
    identity = {"task": TASK, "robot": robot.name, "robot_hash": robot.hash, "seed": 0, "ranges": {},
                "validation": config.as_dict(), "keep_gains": False, "source": "human",
                "files": [f.name for f in files], "retarget": asdict(settings)}
    run = {"started": datetime.now(timezone.utc).isoformat(timespec="seconds"), "command": command, "n": len(files),
           "workers": 1, "backend": "process", "provenance": provenance(robot.hash)}
    store = DatasetStore(out)
    with store.lock():
        _extend_clip_list(Path(out), identity)
        _, outcomes = store.prepare(identity, run)
        todo = [i for i in range(len(files)) if i not in outcomes]
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(todo), desc="retarget", unit="clip", dynamic_ncols=True)
        for i in todo:
            outcome = _one(robot, motions[i], i, settings, config, command, store)
            outcomes[i] = outcome
            why = f": {', '.join(outcome.reasons)}" if outcome.reasons else ""
            log(f"{files[i].name}: {outcome.status}{why}{' (' + outcome.message + ')' if outcome.message else ''}")
            if bar is not None:
                bar.update(1)
        if bar is not None:
            bar.close()
        summary = summarize(dict(sorted(outcomes.items())), identity, len(files))
        store.write_summary(summary)
    return summary


def _extend_clip_list(out: Path, identity: dict[str, Any]) -> None:
    """A dataset of the first of these clips, otherwise the same, takes the longer list (with the
    lock held). Any other difference is left for `DatasetStore.prepare` to name."""
    if not (out / HEADER).is_file():
        return
    header = read_header(out)
    theirs, mine = header["identity"], json.loads(json.dumps(identity))
    done, files = theirs.get("files"), mine["files"]
    rest_equal = {k: v for k, v in theirs.items() if k != "files"} == {k: v for k, v in mine.items() if k != "files"}
    if isinstance(done, list) and len(done) < len(files) and files[:len(done)] == done and rest_equal:
        header["identity"] = {**theirs, "files": files}
        write_json(out / HEADER, header)


def _one(robot, motion: HumanMotion, index: int, settings: RetargetSettings, config: ValidationConfig,
         command: str, store: DatasetStore) -> Outcome:
    try:
        traj, task_errors = retarget(robot, motion, settings)
    except (DataError, ConfigError) as exc:  # e.g. a skeleton without the joints the keypoints need
        outcome = Outcome(index, FAILED, {}, ["error"], str(exc))
        store.write_failure(outcome)
        return outcome
    traj.provenance.update(index=index, dataset_seed=0, command=command)
    v = traj.validation = validate(robot, traj, config, task_errors)
    outcome = Outcome(index, ACCEPTED if v["accepted"] else REJECTED, dict(traj.params), list(v["reasons"]),
                      solve_time=traj.solver["total_time"], validation_time=v["time"],
                      iterations=traj.solver["iterations"], figures=dict(v["figures"]), limits=dict(v["limits"]),
                      units=dict(v["units"]))
    store.write_trajectory(outcome, traj)
    return outcome
