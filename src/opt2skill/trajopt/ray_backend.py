"""Dataset generation on Ray: each trajectory a task (one CPU, no retries), same results as the pool.

Without an address a local Ray instance is started with `workers` CPUs; with `--address` the
driver joins a running cluster (every node needs opt2skill installed). The driver keeps at most
`workers` tasks (default: the cluster's CPUs) in flight, so results stream back to it and a task
starts about when it is submitted (which is what the per-task timeout measures).
"""

from __future__ import annotations

import time
from collections.abc import Iterator

from opt2skill.trajopt.jobs import ERROR, TIMEOUT, WORKER_CRASH, Job, Result, failure, run_job

_ENV = {"env_vars": {"OMP_NUM_THREADS": "1"}}  # in every Ray worker, before Crocoddyl loads


def ray_results(jobs: list[Job], workers: int, address: str | None, timeout: float | None) -> Iterator[Result]:
    import ray
    import ray.exceptions

    started_here = not ray.is_initialized()
    if started_here:
        if address:
            ray.init(address=address, runtime_env=_ENV, log_to_driver=False)
        else:
            ray.init(num_cpus=workers or None, include_dashboard=False, runtime_env=_ENV, log_to_driver=False)
    in_flight = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
    remote = ray.remote(num_cpus=1, max_retries=0)(run_job).options(runtime_env=_ENV)
    queue = list(reversed(jobs))
    pending: dict = {}  # ObjectRef -> (job, submit time)
    try:
        while queue or pending:
            while queue and len(pending) < in_flight:
                job = queue.pop()
                pending[remote.remote(job)] = (job, time.monotonic())
            done, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in done:
                job, _ = pending.pop(ref)
                try:
                    yield ray.get(ref)
                except ray.exceptions.RayTaskError as exc:  # raised inside run_job: not one of its own errors
                    yield failure(job, ERROR, str(exc.cause if exc.cause is not None else exc).splitlines()[0])
                except ray.exceptions.RayError as exc:  # the worker died, ran out of memory, ...
                    yield failure(job, WORKER_CRASH, f"{type(exc).__name__}: {str(exc).splitlines()[0]}")
            if timeout is not None:
                now = time.monotonic()
                for ref, (job, submitted) in list(pending.items()):
                    if now - submitted > timeout:
                        ray.cancel(ref, force=True)
                        del pending[ref]
                        yield failure(job, TIMEOUT, f"no result within {timeout:g} s")
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
        if started_here:
            ray.shutdown()
