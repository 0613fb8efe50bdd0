"""Dataset generation: one solve per process, every outcome recorded, resumable after a kill.

The driver samples the parameters of trajectory i with `ParamSpace.sample(seed, i)`, sends jobs to
a backend (a process pool here, Ray in `ray_backend`), and writes each result as it arrives into a
`DatasetStore` (atomic per-trajectory files). Rerunning the same command skips every index already
recorded; a larger --n adds the missing indices; other settings into the same directory are an
error naming the difference, and so are task settings other than those the recorded trajectories
were solved with (a default changed by a newer version included: they are in each trajectory's
provenance). Only the `Task` interface and the registry are used.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from opt2skill.data.store import ACCEPTED, FAILED, REJECTED, DatasetStore, Outcome
from opt2skill.data.summary import summarize
from opt2skill.data.validate import ValidationConfig
from opt2skill.errors import ConfigError, DataError
from opt2skill.output_paths import check_output_dir
from opt2skill.provenance import provenance
from opt2skill.trajopt.jobs import Job, Result, failure, run_job
from opt2skill.trajopt.process_pool import run_jobs

SUMMARY_EVERY = 10.0  # s between summary rewrites during a run (and once at the end)


@dataclass(frozen=True)
class GenerateRequest:
    task: str
    n: int
    seed: int = 0
    out: Path = Path("data")
    robot: str = "digit"
    workers: int = 0  # 0: every CPU (process pool) or every CPU of the cluster (Ray)
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)  # --set name=lo:hi
    limits: dict[str, Any] = field(default_factory=dict)  # validation limit overrides
    keep_gains: bool = False
    retry_failed: bool = False
    timeout: float | None = None  # s per trajectory; None: no limit
    task_config: dict[str, Any] = field(default_factory=dict)  # task config overrides (e.g. duration); in the identity
    ray: bool = False
    ray_address: str | None = None
    command: str = ""


def process_results(jobs: list[Job], workers: int, timeout: float | None) -> Iterator[Result]:
    """Results in completion order from `workers` processes (a crash or a timeout costs one item)."""
    return run_jobs(run_job, jobs, workers, timeout, failure)


def _parse_task(request: GenerateRequest):
    """Robot, parameter space (with --set ranges), validation config and the task's resolved settings
    (as its trajectories' provenance records them); errors before any work."""
    from opt2skill.model import load_robot
    from opt2skill.tasks import get_task
    from opt2skill.trajopt.config import config_to_dict

    robot = load_robot(request.robot)
    task = get_task(request.task, robot, _overrides(request))
    space = task.param_space()
    for name, bounds in request.ranges.items():
        space.set_range(name, bounds)
    config = ValidationConfig().with_overrides(request.limits)
    return robot, space, config, json.loads(json.dumps(config_to_dict(task.config)))


def _overrides(request: GenerateRequest) -> dict[str, Any]:
    # Gains are always computed (free in DDP) for the feedback replay of validation; the store
    # drops them unless --keep-gains. Kinematic tasks (IK) have no solver gains.
    from opt2skill.tasks import task_info

    task = task_info(request.task).task
    gains = {"solver.keep_gains": True} if task is None or task.has_dynamics else {}
    return {**request.task_config, **gains}


def _check_same_settings(store: DatasetStore, outcomes: dict[int, Outcome], settings: dict[str, Any]) -> None:
    """DataError unless the newest recorded trajectory was solved with these task settings: a resumed
    dataset must not mix references of two optimizer settings, as it would after an upgrade that
    changed a default. Settings one side does not have (a field added since, at its default, which
    keeps the old behaviour) are not compared, nor are records without settings in their provenance."""
    from opt2skill.data.trajfile import read_meta

    solved = [o for o in outcomes.values() if o.status != FAILED]
    if not solved:
        return
    newest = max(solved, key=lambda o: o.index)
    recorded = read_meta(store.path(newest.status, newest.index)).provenance.get("task_config")
    if recorded is None:
        return
    diffs = _differences(recorded, settings)
    if diffs:
        shown = "; ".join(diffs[:5]) + (f"; and {len(diffs) - 5} more" if len(diffs) > 5 else "")
        raise DataError(f"{store.root} was solved with other task settings than this command's ({shown}); "
                        "resume it with the settings it was made with (--config KEY=VALUE for each, or the "
                        "version that made it), or use another --out")


def _differences(recorded: dict[str, Any], current: dict[str, Any], prefix: str = "") -> list[str]:
    """'key: recorded A, this command B' for each (dotted) key both have with other values."""
    out = []
    for key in sorted(set(recorded) & set(current)):
        a, b = recorded[key], current[key]
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key}: recorded {json.dumps(a)}, this command {json.dumps(b)}")
    return out


def generate(request: GenerateRequest, progress: bool = True) -> dict[str, Any]:
    """Generate (or resume) the dataset of `request`; returns its summary."""
    if request.n < 1:
        raise ConfigError(f"--n must be >= 1 (the number of trajectories, indices 0 .. n-1), got {request.n}")
    check_output_dir(request.out)
    if request.timeout is not None and request.timeout <= 0:
        raise ConfigError(f"--timeout must be > 0 seconds, got {request.timeout:g}")
    os.environ["OMP_NUM_THREADS"] = "1"  # inherited by every worker before it loads Crocoddyl
    robot, space, config, settings = _parse_task(request)
    identity = {
        "task": request.task,
        "robot": robot.name,
        "robot_hash": robot.hash,
        "seed": request.seed,
        "ranges": {name: list(bounds) for name, bounds in space.ranges.items()},
        "validation": config.as_dict(),
        "keep_gains": request.keep_gains,
    }
    if request.task_config:  # only when set: datasets made before this field keep their identity
        identity["task_config"] = dict(sorted(request.task_config.items()))
    workers = request.workers or (os.cpu_count() or 1)
    run = {
        "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": request.command,
        "n": request.n,
        "workers": workers,
        "backend": "ray" if request.ray else "process",
        "provenance": provenance(robot.hash),
    }
    store = DatasetStore(request.out)
    with store.lock():
        _, outcomes = store.prepare(identity, run)
        _check_same_settings(store, outcomes, settings)
        redo = {FAILED} if request.retry_failed else set()
        todo = [i for i in range(request.n) if i not in outcomes or outcomes[i].status in redo]
        jobs = [
            Job(request.task, request.robot, _overrides(request), i, request.seed, space.sample(request.seed, i),
                config.as_dict(), request.command)
            for i in todo
        ]
        requested = max(request.n, max(outcomes, default=-1) + 1)
        if request.ray:
            from opt2skill.trajopt.ray_backend import ray_results

            results = ray_results(jobs, request.workers, request.ray_address, request.timeout)
        else:
            results = process_results(jobs, min(workers, max(len(jobs), 1)), request.timeout)
        drop = () if request.keep_gains else ("gains",)
        bar = _progress(request.task, len(jobs), len(outcomes), progress)
        last_summary = time.monotonic()
        try:
            for result in results:
                outcome = result.outcome
                if result.traj is not None:
                    store.write_trajectory(outcome, result.traj, drop_knots=drop)
                else:
                    store.write_failure(outcome)
                outcomes[outcome.index] = outcome
                _advance(bar, outcomes)
                if time.monotonic() - last_summary > SUMMARY_EVERY:
                    store.write_summary(summarize(outcomes, identity, requested))
                    last_summary = time.monotonic()
        finally:
            results.close()
            if bar is not None:
                bar.close()
            summary = summarize(dict(sorted(outcomes.items())), identity, requested)
            store.write_summary(summary)
    return summary


def _progress(task: str, total: int, done_before: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    desc = f"{task}" + (f" ({done_before} done before)" if done_before else "")
    return tqdm(total=total, desc=desc, unit="traj", dynamic_ncols=True, smoothing=0.1)


def _advance(bar, outcomes: dict[int, Outcome]) -> None:
    if bar is None:
        return
    counts = {s: 0 for s in (ACCEPTED, REJECTED, FAILED)}
    for o in outcomes.values():
        counts[o.status] += 1
    bar.set_postfix(counts, refresh=False)
    bar.update(1)
