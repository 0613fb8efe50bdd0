"""One dataset item as a unit of work: solve, validate, return the record or the reason it failed.

`run_job` runs in a worker process (process pool or Ray task). It only uses the `Task` interface and
the registry, and turns every error of its own item into a failure outcome, so one bad trajectory
never stops a batch. Worker crashes and timeouts are caught by the backends (`failure`).
"""

from __future__ import annotations

import json
import socket
import time
import traceback
from dataclasses import dataclass
from typing import Any

from opt2skill.data.record import Trajectory
from opt2skill.data.store import ACCEPTED, FAILED, REJECTED, Outcome
from opt2skill.errors import SolverError
from opt2skill.trajopt.process_pool import ERROR, TIMEOUT, WORKER_CRASH  # noqa: F401  (failure kinds)

# Failure kinds (the `reasons` of a failed outcome), besides WORKER_CRASH, TIMEOUT and ERROR.
SOLVER_ERROR, VALIDATION_ERROR = "solver_error", "validation_error"


@dataclass(frozen=True)
class Job:
    task: str
    robot: str
    overrides: dict[str, Any]
    index: int
    seed: int
    params: dict[str, float]
    validation: dict[str, Any]  # ValidationConfig.as_dict()
    command: str


@dataclass
class Result:
    outcome: Outcome
    traj: Trajectory | None = None


def failure(job: Job, kind: str, message: str, solve_time: float | None = None) -> Result:
    return Result(Outcome(job.index, FAILED, dict(job.params), [kind], message, solve_time=solve_time))


_loaded: dict[str, Any] = {}  # per worker process: robot, task and validation config of the last job kind


def _load(job: Job) -> tuple[Any, Any, Any]:
    key = json.dumps([job.task, job.robot, job.overrides, job.validation], sort_keys=True)
    if _loaded.get("key") != key:
        from opt2skill.data.validate import ValidationConfig
        from opt2skill.model import load_robot
        from opt2skill.tasks import get_task

        robot = load_robot(job.robot)
        _loaded.update(key=key, robot=robot, task=get_task(job.task, robot, job.overrides),
                       config=ValidationConfig.from_dict(job.validation))
    return _loaded["robot"], _loaded["task"], _loaded["config"]


def _error_message(exc: BaseException) -> str:
    where = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
    suffix = f" (at {where.filename}:{where.lineno})" if where else ""
    return f"{type(exc).__name__}: {exc}{suffix}"


def run_job(job: Job) -> Result:
    """Solve and validate trajectory `job.index`; never raises for a problem of this item."""
    from opt2skill.data.validate import validate

    robot, task, config = _load(job)
    start = time.perf_counter()
    try:
        traj = task.solve(job.params, job.seed)
    except SolverError as exc:
        return failure(job, SOLVER_ERROR, str(exc), time.perf_counter() - start)
    except Exception as exc:  # a bug or a library error on this item: recorded, the batch goes on
        return failure(job, ERROR, _error_message(exc), time.perf_counter() - start)
    solve_time = time.perf_counter() - start
    traj.solver.setdefault("total_time", solve_time)  # wall time of the whole solve, frames included
    traj.provenance.update(index=job.index, dataset_seed=job.seed, command=job.command, host=socket.gethostname())
    try:
        traj.validation = validate(robot, traj, config, task.task_errors(traj))
    except Exception as exc:
        return failure(job, VALIDATION_ERROR, _error_message(exc), solve_time)
    v = traj.validation
    outcome = Outcome(
        index=job.index,
        status=ACCEPTED if v["accepted"] else REJECTED,
        params=dict(traj.params),
        reasons=list(v["reasons"]),
        solve_time=traj.solver["total_time"],
        validation_time=v["time"],
        iterations=traj.solver.get("iterations"),
        figures=dict(v["figures"]),
        limits=dict(v["limits"]),
        units=dict(v["units"]),
    )
    return Result(outcome, traj)
