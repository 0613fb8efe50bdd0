"""Data-parallel PPO over several processes: each trains on worlds of its own, gradients averaged.

rsl_rl's PPO already knows how (its `multi_gpu` settings): it averages the gradients and the
adaptive learning rate's KL over `torch.distributed`, and its observation normalizers average their
statistics there too. This module supplies the process group and the few decisions our loop must
take together: whether to checkpoint (rank 0's clock decides), and the iteration's figures (the mean
over the processes, rates summed), so that every process runs the same sequence of collective
calls and an adaptive curriculum moves the same way everywhere.

A group's learners stay on the CPU (gloo backend) whatever the physics device; process r steps its
physics on `cuda:r` with `--device cuda` under `torchrun` on a multi-GPU machine, and on CPU cores
otherwise. Two ways to start:

    opt2skill train ... --procs 2                      # this machine, 2 processes (spawned here)
    torchrun --standalone --nproc-per-node 8 -m opt2skill train ...  # torchrun's processes
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from opt2skill.errors import Opt2SkillError

# Figures that are counts or rates of one process's worlds: the group's is their sum, not their mean.
SUMMED = ("perf/env_steps_per_s", "perf/learner_samples_per_s", "episode/count", "randomization/pushes")
SUMMED_PREFIXES = ("terminations/",)


def summed(key: str) -> bool:
    return key in SUMMED or key.startswith(SUMMED_PREFIXES)


@dataclass(frozen=True)
class Group:
    """This process's place in a data-parallel training (rank 0 writes the run)."""

    rank: int
    size: int
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def rsl_rl(self) -> dict[str, int] | None:
        """rsl_rl's `multi_gpu` settings (None for one process)."""
        if self.size == 1:
            return None
        return {"global_rank": self.rank, "local_rank": self.local_rank, "world_size": self.size}

    def seed(self, seed: int) -> int:
        """This process's seed: `seed` itself on rank 0 (one process trains exactly as before), an
        independent stream derived from (seed, rank) on the others."""
        if self.rank == 0:
            return seed
        return int(np.random.SeedSequence([seed, self.rank]).generate_state(1)[0])

    def decide(self, value: Any) -> Any:
        """Rank 0's `value` on every process (a decision all must take together)."""
        if self.size == 1:
            return value
        box = [value]
        torch.distributed.broadcast_object_list(box, src=0)
        return box[0]

    def combine(self, figures: dict[str, float]) -> dict[str, float]:
        """The group's figures of an iteration: per key the mean over the processes that have it
        (an episode figure exists only where episodes ended); counts and throughput rates summed."""
        if self.size == 1:
            return figures
        everyone: list[dict[str, float]] = [{} for _ in range(self.size)]
        torch.distributed.all_gather_object(everyone, figures)
        keys = sorted({k for f in everyone for k in f})
        combined = {}
        for key in keys:
            values = [f[key] for f in everyone if key in f]
            combined[key] = float(np.sum(values) if summed(key) else np.mean(values))
        return combined

    def everyone(self, flag: bool) -> bool:
        """Whether `flag` holds on every process (a condition all must agree on before a collective step)."""
        if self.size == 1:
            return bool(flag)
        value = torch.tensor([1 if flag else 0], dtype=torch.int64)
        torch.distributed.all_reduce(value, op=torch.distributed.ReduceOp.MIN)
        return bool(value.item())

    def share_module(self, module: torch.nn.Module) -> None:
        """Rank 0's parameters and buffers (normalizer statistics included) on every process."""
        if self.size > 1:
            for tensor in module.state_dict().values():
                torch.distributed.broadcast(tensor, src=0)

    def average_gradients(self, parameters) -> None:
        """Each parameter's gradient averaged over the group (rsl_rl's bucketed all-reduce)."""
        if self.size > 1:
            from rsl_rl.utils.utils import reduce_gradients_in_buckets

            reduce_gradients_in_buckets(parameters, self.size, 25)

    def stop_requested(self) -> bool:
        """Whether any process of the group was asked to stop (SIGTERM or Ctrl-C, where
        `stop_together_on_signals` set the handlers: `launch`'s processes and an experiment's side by
        side trainings): checked by every process at the end of an iteration, so that they stop
        together there (rank 0 then checkpoints) instead of one dying inside a collective the others
        wait in, or inside an update that would leave nothing to save."""
        if self.size == 1:
            return _stop[0]
        value = torch.tensor([1 if _stop[0] else 0], dtype=torch.int64)
        torch.distributed.all_reduce(value, op=torch.distributed.ReduceOp.MAX)
        return bool(value.item())

    def barrier(self) -> None:
        if self.size > 1:
            torch.distributed.barrier()


ONE = Group(0, 1)
RENDEZVOUS_FILE = "OPT2SKILL_RENDEZVOUS_FILE"  # set by `launch` for its processes


def from_environment() -> Group:
    """The group torchrun (or `launch`) described in the environment; one process without one."""
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        return ONE
    return Group(int(os.environ["RANK"]), size, int(os.environ.get("LOCAL_RANK", os.environ["RANK"])))


def join(group: Group) -> None:
    """Join the process group (gloo: the learner is on the CPU). No-op for one process or if joined.
    `launch`'s processes meet at a file (no port to race for); torchrun's at its own address."""
    if group.size > 1 and not torch.distributed.is_initialized():
        meeting = os.environ.get(RENDEZVOUS_FILE)
        init = f"file://{meeting}" if meeting else "env://"
        torch.distributed.init_process_group("gloo", init_method=init, rank=group.rank, world_size=group.size)


def leave(group: Group) -> None:
    if group.size > 1 and torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()


def launch(nprocs: int, target: Callable[..., Any], *args: Any) -> Any:
    """Run `target(*args)` in `nprocs` processes of one group on this machine; rank 0's return value.

    The processes are spawned (not forked: MuJoCo's and torch's thread pools do not survive a fork)
    and meet at a file in a fresh temporary folder. If one fails, the others are stopped and its
    error is raised: an input or data error as itself (one line at the command line), else torch's
    report with the child's traceback. Ctrl-C or SIGTERM here is passed on to every process, which
    stop together at the end of the iteration in flight (rank 0 checkpoints, as one process does on
    an interrupt), and waited for."""
    import tempfile

    import torch.multiprocessing as mp
    from torch.multiprocessing.spawn import ProcessException

    results = mp.get_context("spawn").SimpleQueue()
    with tempfile.TemporaryDirectory(prefix="opt2skill-group-") as folder:
        meeting = os.path.join(folder, "rendezvous")
        context = mp.start_processes(_child, args=(nprocs, meeting, results, target, args), nprocs=nprocs,
                                     join=False, start_method="spawn")
        try:
            while not context.join():
                pass
        except KeyboardInterrupt:
            _interrupt(context.processes)
            raise
        except ProcessException:
            found = None if results.empty() else results.get()
            if isinstance(found, Opt2SkillError):
                raise found from None
            raise
    return results.get()


def _interrupt(children, wait: float = 120.0) -> None:
    """SIGTERM to each living child (the group stops at its iteration's end), then wait for all."""
    for child in children:
        if child.is_alive():
            with contextlib.suppress(ProcessLookupError):
                os.kill(child.pid, signal.SIGTERM)
    for child in children:
        child.join(wait)
        if child.is_alive():
            child.kill()


_stop = [False]  # set by a signal in a process of `launch`'s group


def _request_stop(signum, frame) -> None:
    _stop[0] = True


def terminate_as_interrupt() -> None:
    """SIGTERM ends a command like Ctrl-C (a KeyboardInterrupt: a trainer checkpoints what it has
    before exiting, a batch job keeps what it wrote). A process started by torchrun stops with its
    group at the end of the iteration instead (`stop_together_on_signals`)."""
    if from_environment().size > 1:
        stop_together_on_signals()
        return

    def handler(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, handler)


@contextlib.contextmanager
def interrupts_held():
    """Ctrl-C and SIGTERM that arrive inside the block are handled when it ends, by the handlers they
    would have met then: a block that must not be cut in two (a learning step with its counters and
    its log line) ends whole, and the interrupt takes effect right after it. Only Python handlers are
    held (a default SIGTERM still kills at once), only in the main thread (where Python handles
    signals), and a block that raises drops what it held (its exception ends the command anyway)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    previous = {signum: handler for signum, handler in previous.items() if callable(handler)}
    for signum in previous:
        signal.signal(signum, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    for signum in dict.fromkeys(held):  # each signal once, in the order they came
        previous[signum](signum, None)


def interrupt_children() -> None:
    """SIGTERM to this process's living multiprocessing children: their trainings stop at the end of
    the iteration in flight and checkpoint (waiting for them is the caller's: a pool's workers
    outlive their tasks)."""
    import multiprocessing

    for child in multiprocessing.active_children():
        with contextlib.suppress(ProcessLookupError):
            os.kill(child.pid, signal.SIGTERM)


def stop_together_on_signals() -> None:
    """SIGTERM and Ctrl-C make this process of a group stop with the others at the end of the
    iteration in flight (`Group.stop_requested`), not die inside a collective."""
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, _request_stop)


def _child(rank: int, nprocs: int, meeting: str, results, target: Callable[..., Any], args: tuple) -> None:
    stop_together_on_signals()
    os.environ.update({RENDEZVOUS_FILE: meeting, "WORLD_SIZE": str(nprocs), "RANK": str(rank),
                       "LOCAL_RANK": str(rank)})
    group = from_environment()
    join(group)
    try:
        try:
            result = target(*args)
        except Opt2SkillError as exc:  # for the parent to raise as itself
            results.put(exc)
            raise SystemExit(2) from None
        if group.is_main:
            results.put(result)
    finally:
        leave(group)
