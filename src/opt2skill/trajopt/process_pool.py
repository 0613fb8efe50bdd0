"""A pool of worker processes that attributes every crash and timeout to the one job it cost.

Each worker is a spawned process with its own pipe and runs one job at a time, so the driver always
knows which job a dead worker held: it records that job as a failure, starts a new worker and goes
on. (concurrent.futures breaks the whole pool on a crash; pebble does too when a worker dies before
acknowledging its job.) Workers die with the driver (Linux) and ignore Ctrl-C, which the driver
handles.
"""

from __future__ import annotations

import multiprocessing
import signal
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any

POLL = 0.5  # s between timeout checks
WORKER_CRASH, TIMEOUT, ERROR = "worker_crash", "timeout", "error"  # the kinds passed to `on_failure`


@dataclass(frozen=True)
class _Raised:
    message: str


def _die_with_parent() -> None:
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the worker exits at its next receive instead
        pass


def _serve(conn: Connection, function: Callable[[Any], Any]) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent()
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        try:
            result = function(job)
        except Exception as exc:  # reported as this job's failure; the worker stays
            result = _Raised(f"{type(exc).__name__}: {exc}")
        conn.send(result)


@dataclass
class _Worker:
    process: Any
    conn: Connection
    job: Any = None
    since: float = 0.0


def run_jobs(
    function: Callable[[Any], Any],
    jobs: list[Any],
    workers: int,
    timeout: float | None,
    on_failure: Callable[[Any, str, str], Any],
) -> Iterator[Any]:
    """Yields `function(job)` for every job in completion order, or `on_failure(job, kind, message)`
    with kind WORKER_CRASH, TIMEOUT or ERROR (`function` raised). `function` must be importable (it is sent to spawned
    processes by reference)."""
    context = multiprocessing.get_context("spawn")

    def start() -> _Worker:
        parent, child = context.Pipe()
        process = context.Process(target=_serve, args=(child, function), daemon=True)
        process.start()
        child.close()
        return _Worker(process, parent)

    def stop(worker: _Worker) -> None:
        worker.process.kill()
        worker.process.join()
        worker.conn.close()

    pending = deque(jobs)
    pool = [start() for _ in range(max(1, min(workers, len(jobs))))]
    try:
        while pending or any(w.job is not None for w in pool):
            for i, w in enumerate(pool):
                if w.job is None and pending:
                    job = pending.popleft()
                    try:
                        w.conn.send(job)
                    except (BrokenPipeError, OSError):  # died while idle: not this job's fault
                        pending.appendleft(job)
                        stop(w)
                        pool[i] = start()
                        continue
                    w.job, w.since = job, time.monotonic()
            busy = [w for w in pool if w.job is not None]
            wait([w.conn for w in busy] + [w.process.sentinel for w in busy], timeout=POLL)
            for i, w in enumerate(pool):
                if w.job is None:
                    continue
                job = w.job
                if w.conn.poll():
                    try:
                        result = w.conn.recv()
                    except (EOFError, OSError):
                        result = None
                    if result is not None:
                        w.job = None
                        yield on_failure(job, ERROR, result.message) if isinstance(result, _Raised) else result
                        continue
                if not w.process.is_alive() or w.conn.closed:
                    w.process.join()
                    code = w.process.exitcode
                    stop(w)
                    pool[i] = start()
                    yield on_failure(job, WORKER_CRASH, f"worker process died (exit code {code})")
                elif timeout is not None and time.monotonic() - w.since > timeout:
                    stop(w)
                    pool[i] = start()
                    yield on_failure(job, TIMEOUT, f"no result within {timeout:g} s")
    finally:
        for w in pool:
            if w.job is None and not w.conn.closed:
                try:
                    w.conn.send(None)
                except (BrokenPipeError, OSError):
                    pass
            w.process.join(timeout=1.0 if w.job is None else 0.0)
            if w.process.is_alive():
                w.process.kill()
                w.process.join()
            w.conn.close()
