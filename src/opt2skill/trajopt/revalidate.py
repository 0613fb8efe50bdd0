"""Re-check a stored dataset: recompute every trajectory's validation and compare with what is stored.

Validation is deterministic (same code, same libraries, same stored arrays: same figures), so any
difference means the data, the code or the libraries changed since the dataset was written. Task
errors come from the dataset's task in the registry, as during generation.
"""

from __future__ import annotations

import concurrent.futures
import math
import multiprocessing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from opt2skill.data.file_check import BadFiles, scan
from opt2skill.data.reader import Dataset
from opt2skill.data.store import ACCEPTED, REJECTED
from opt2skill.data.validate import ValidationConfig
from opt2skill.errors import DataError

RTOL, ATOL = 1e-6, 1e-9


@dataclass
class Recheck:
    index: int
    status: str  # where it is stored: accepted | rejected
    stored: dict[str, Any]
    new: dict[str, Any]


@dataclass
class RevalidationReport:
    checks: list[Recheck]
    limits: dict[str, float | None]
    disagreements: list[tuple[int, str, Any, Any]] = field(default_factory=list)  # index, figure, stored, new
    decision_changes: list[tuple[int, str, list[str]]] = field(default_factory=list)  # index, stored status, reasons now
    not_recomputed: set[str] = field(default_factory=set)  # stored figures the files cannot reproduce
    bad_files: BadFiles | None = None  # files that could not be re-checked, every one of them


def _close(a: Any, b: Any) -> bool:
    if a is None or b is None:
        return a is None and b is None
    if not (math.isfinite(a) and math.isfinite(b)):
        return str(a) == str(b)
    return abs(a - b) <= ATOL + RTOL * max(abs(a), abs(b))


def compare(stored: dict[str, Any], new: dict[str, Any]) -> list[tuple[str, Any, Any]]:
    """Recomputed figures whose stored value differs (beyond rounding). Figures that cannot be
    recomputed from the file (the feedback replay when the gains were not kept) are not compared."""
    a, b = stored.get("figures", {}), new.get("figures", {})
    return [(name, a.get(name), b[name]) for name in sorted(b) if not _close(a.get(name), b[name])]


_loaded: dict[str, Any] = {}


def _recheck(path: str, status: str, task: str, robot: str, config: dict[str, Any]) -> Recheck:
    from opt2skill.data.trajfile import read_meta, read_trajectory
    from opt2skill.data.validate import validate
    from opt2skill.model import load_robot
    from opt2skill.tasks import get_task, task_info

    key = (task, robot)
    if _loaded.get("key") != key:
        loaded_robot = load_robot(robot)
        # A task whose references are not generated (retargeted clips) has no task checks.
        made = get_task(task, loaded_robot) if task_info(task).task is not None else None
        _loaded.update(key=key, robot=loaded_robot, task=made)
    traj = read_trajectory(path)
    errors = _loaded["task"].task_errors(traj) if _loaded["task"] is not None else {}
    new = validate(_loaded["robot"], traj, ValidationConfig.from_dict(config), errors)
    return Recheck(read_meta(path).index, status, traj.validation, new)


def revalidate(
    root: str | Path,
    workers: int = 1,
    robot: str | None = None,
    limits: dict[str, Any] | None = None,
    progress: bool = False,
) -> RevalidationReport:
    """Recompute the validation of every accepted and rejected trajectory of the dataset at `root`.

    `robot`: name or robot.yaml path, when the dataset's robot is not a built-in one.
    """
    datasets = {status: Dataset.open(root, status) for status in (ACCEPTED, REJECTED)}
    identity = datasets[ACCEPTED].identity
    config = ValidationConfig.from_dict(identity["validation"]).with_overrides(limits or {})
    items, problems = [], []
    for status, ds in datasets.items():  # every bad file is reported, not only the first
        good, bad = scan(ds.files, identity)
        items += [(str(p), status) for p in good]
        problems += bad
    # Gains and the task matter for the figures: the registry gives the task of the dataset.
    args = (identity["task"], robot or identity["robot"], config.as_dict())
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(items), desc="validate", unit="traj", dynamic_ncols=True)
    checks = []
    if workers <= 1 or len(items) <= 1:
        for path, status in items:
            try:
                checks.append(_recheck(path, status, *args))
            except DataError as exc:  # unreadable arrays, NaN or infinity
                problems.append(str(exc))
            if bar is not None:
                bar.update(1)
    else:
        context = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(min(workers, len(items)), mp_context=context) as pool:
            futures = [pool.submit(_recheck, path, status, *args) for path, status in items]
            for future in concurrent.futures.as_completed(futures):
                try:
                    checks.append(future.result())
                except DataError as exc:
                    problems.append(str(exc))
                if bar is not None:
                    bar.update(1)
    if bar is not None:
        bar.close()
    checks.sort(key=lambda c: c.index)
    report = RevalidationReport(checks=checks, limits=dict(config.limits))
    if problems:
        report.bad_files = BadFiles(Path(root), datasets[ACCEPTED].header, sorted(problems))
    for c in checks:
        report.disagreements += [(c.index, *d) for d in compare(c.stored, c.new)]
        report.not_recomputed |= set(c.stored.get("figures", {})) - set(c.new["figures"])
        if c.new["accepted"] != (c.status == ACCEPTED):
            report.decision_changes.append((c.index, c.status, list(c.new["reasons"])))
    return report
