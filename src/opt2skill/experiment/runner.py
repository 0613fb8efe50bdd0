"""What every experiment command does around its own steps: one writer per folder, the folder's
identity, the step counter, training a policy, the provenance file, and the list of outputs."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from opt2skill.cli.console import console
from opt2skill.experiment.settings import Settings, claim_folder
from opt2skill.experiment.steps import DONE, Steps, Unavailable
from opt2skill.rl.run import PROGRESS_FILE, read_progress


def run_experiment(s: Settings, out: Path, total: int, body: Callable[[Path, Steps], dict[str, Path]]) -> dict[str, Path]:
    """Check `s`, lock and claim `out`, run `body(out, steps)` (the experiment's steps; it returns
    its outputs), write the provenance and print where each output is."""
    from opt2skill.folder_lock import folder_lock
    from opt2skill.output_paths import check_output_dir

    s.check()
    os.environ["OMP_NUM_THREADS"] = "1"  # before Crocoddyl loads, here and in every generation worker
    out = Path(check_output_dir(out))
    steps = Steps(out, total=total)
    started = time.perf_counter()
    with folder_lock(out):
        claim_folder(out, s)  # under the lock: two runs cannot both claim an empty folder
        outputs = body(out, steps)
        outputs["provenance"] = out / "provenance.json"
        outputs["steps (one file per finished step)"] = steps.folder
        write_provenance(s, out, steps, time.perf_counter() - started)
    console.rule("[bold]done")
    for what, where in outputs.items():  # plain lines: a table would cut long paths
        console.print(f"{what}: {where}", soft_wrap=True, highlight=False)
    return outputs


def need(steps: Steps, name: str, what: str) -> dict[str, Any]:
    """The result of finished step `name`; `Unavailable` (with its reason) when it is not done."""
    record = steps.record(name)
    if record is None or record["status"] != DONE:
        reason = (record or {}).get("result", {}).get("reason", "not run")
        raise Unavailable(f"no {what} ({reason})")
    return record["result"]


def done(steps: Steps, name: str) -> dict[str, Any] | None:
    """The result of step `name` when it finished, else None."""
    record = steps.record(name) or {}
    return record["result"] if record.get("status") == DONE else None


def run_dir(out: Path, key: str) -> Path:
    return Path(out) / "runs" / key


def train_request(s: Any, out: Path, key: str, data: dict[str, Any], ablation: str, history: int, command: str,
                  threads: int | None = None):
    """The `train` request of policy KEY: every policy of an experiment with the settings' budget and options."""
    from opt2skill.rl import session

    return session.TrainRequest(dataset=Path(data["dataset"]), out=run_dir(out, key), steps=s.train_steps,
                                num_envs=s.num_envs, history=history, ablation=ablation, seed=training_seed(s),
                                command=command,
                                device=s.device, threads=threads, mixed_precision=s.mixed_precision,
                                base_position=getattr(s, "base_position", "task"),
                                noise_min=getattr(s, "noise_min", 1.0),
                                rewards=tuple(tuple(change) for change in getattr(s, "rewards", ())))


def training_seed(s: Any) -> int:
    """Every policy's training seed: the settings' `train_seed` where they have one, else their `seed`."""
    train_seed = getattr(s, "train_seed", None)
    return s.seed if train_seed is None else train_seed


def training_note(s: Any) -> str:
    """What every policy's training did beyond the paper's, for a table's notes: bf16 PPO updates,
    the base-position term, each world's own share of the observation noise, reward terms changed
    ("" when none)."""
    parts = []
    if training_seed(s) != s.seed:
        parts.append(f"training seed {training_seed(s)}, the references' {s.seed} (--train-seed)")
    if s.mixed_precision:
        parts.append("PPO updates in bf16 autocast (--mixed-precision)")
    if getattr(s, "base_position", "task") != "task":
        parts.append(f"the base-position reward {getattr(s, 'base_position')} (--base-position)")
    if getattr(s, "noise_min", 1.0) < 1.0:
        parts.append(f"each world's observation noise at a share drawn in [{s.noise_min:g}, 1] of Table II's "
                     "(--noise-min)")
    for name, weight, scale in getattr(s, "rewards", ()):
        parts.append(f"Table I's {name} term at weight {weight:g}" + (f", kernel scale {scale:g}" if scale is not None
                                                                     else "") + " (--reward)")
    return "".join(", " + part for part in parts)


def train_policy(s: Any, out: Path, key: str, data: dict[str, Any], ablation: str, history: int, command: str,
                 progress: bool, threads: int | None = None) -> dict[str, Any]:
    """A policy on the dataset of finished data step `data` (`s`: train_steps, num_envs, seed or train_seed, device,
    mixed_precision and, where the settings have them, distill_steps, base_position, noise_min and rewards), into OUT/runs/KEY; resumes from
    the run's newest checkpoint. PPO from scratch, or after distilling the optimizer's feedback expert
    when `s.distill_steps` > 0 (rl.distill_session). `threads`: physics and torch threads (None: every core)."""
    from opt2skill.rl import distill_session, session

    request = train_request(s, out, key, data, ablation, history, command, threads)
    announce = lambda line: console.print(line, highlight=False)  # noqa: E731
    distill_steps = getattr(s, "distill_steps", 0)
    start = time.perf_counter()
    if distill_steps > 0:
        result = distill_session.train(request, distill_steps, progress=progress, announce=announce)
    else:
        result = session.train(request, progress=progress, announce=announce)
    elapsed = time.perf_counter() - start
    return {"run": str(request.out), "ablation": ablation, "history": history, "iteration": result["iteration"],
            "env_steps": result["env_steps"], "train_s": elapsed, "references": data["counts"]["accepted"],
            "distill_env_steps": result.get("distill_env_steps", 0), "policy": str(keep_final_actor(request.out))}


def keep_final_actor(run: Path) -> Path:
    """RUN/final/model.pt, the finished run's actor alone: committed with the experiment's folder
    (its checkpoints are not), so that its policies can be evaluated again on another machine."""
    from opt2skill.rl import checkpoint as checkpoints

    return checkpoints.save_actor(checkpoints.latest(run), checkpoints.final_path(run))


def train_policies_at_once(s: Any, out: Path, jobs: list[tuple[str, dict[str, Any], str, int]], command: str,
                           progress: bool = True) -> None:
    """Train the runs of `jobs` ((key, data step result, ablation, history), those not finished yet) up
    to `s.workers` at a time (0: every core), each in its own process, so that a machine's cores share
    the training; on a GPU (`s.device` not cpu) the training steps train one after another.
    The experiment's training steps then come after, one by one as before: each resumes its run,
    finds it finished, and records it. A run that fails here is only announced: its step trains it
    again and records what happens. `progress`: one bar over all these runs' environment steps, read
    from their progress logs, with an ETA (the processes themselves draw none)."""
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from multiprocessing import get_context

    from opt2skill.rl import processes

    workers = s.workers or os.cpu_count() or 1
    if s.device != "cpu" or workers < 2 or len(jobs) < 2:
        return
    workers = min(workers, len(jobs))
    # The cores shared out: each process with every core's threads would run 2 x workers threads on them.
    threads = max(1, (os.cpu_count() or 1) // workers)
    console.print(f"training {len(jobs)} policies, {workers} at a time in their own processes of {threads} "
                  f"thread{'s' if threads > 1 else ''} ({', '.join(key for key, *_ in jobs)}); each step below then "
                  "records its run", highlight=False)
    runs = [_LoggedSteps(run_dir(out, key)) for key, *_ in jobs]
    bar = _steps_bar(s, runs) if progress else None
    # In each process SIGTERM and Ctrl-C end its training at the end of the iteration in flight,
    # checkpointed (a default SIGTERM would lose everything since the last periodic checkpoint).
    pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=processes.stop_together_on_signals)
    try:
        started = time.perf_counter()
        pending = {pool.submit(train_policy, s, out, key, data, ablation, history, command, False, threads): key
                   for key, data, ablation, history in jobs}
        while pending:
            finished, _ = wait(pending, timeout=10.0, return_when=FIRST_COMPLETED)
            if bar is not None:  # a run stops at the end of its last iteration, a little past its steps
                bar.update(max(0, min(bar.total, sum(run.count() for run in runs)) - bar.n))
            for future in finished:
                key = pending.pop(future)
                try:
                    future.result()
                    line = f"  {key}: ready ({time.perf_counter() - started:.0f} s)"
                except Exception as exc:  # noqa: BLE001 - the step that follows retries it and records the failure
                    line = f"  {key}: failed in its process ({type(exc).__name__}: {exc}); its step retries it"
                (bar.write if bar is not None else lambda text: console.print(text, highlight=False))(line)
    except KeyboardInterrupt:  # stopped here (Ctrl-C, or SIGTERM to this process alone): the trainings too
        console.print(f"stopping: the {len(jobs)} trainings checkpoint at the end of their iteration", highlight=False)
        processes.interrupt_children()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        if bar is not None:
            bar.close()


def _steps_bar(s: Any, runs: list[_LoggedSteps]):
    """A bar over the environment steps of `runs` (distillation and PPO), starting where they resume."""
    from tqdm import tqdm

    per_run = s.train_steps + getattr(s, "distill_steps", 0)
    total = per_run * len(runs)
    return tqdm(total=total, initial=min(total, sum(run.count() for run in runs)), desc="training",
                unit="step", unit_scale=True, dynamic_ncols=True)


class _LoggedSteps:
    """Environment steps a run has logged (its distillation's, `distill/progress.jsonl`, and PPO's),
    counted as its resumption counts them. Lines logged after a stage's newest checkpoint were lost
    with the kill that stopped it: they count only once the resumed run has rewritten its log (a new
    file), so that a bar never starts above where the training restarts and then runs backwards."""

    def __init__(self, run: Path):
        self.stages = [Path(run) / "distill", Path(run)]
        self.stale = {}  # stage -> (its log's inode at the start, steps logged at its newest checkpoint)
        for stage in self.stages:
            log = stage / PROGRESS_FILE
            at_checkpoint = _steps_at_checkpoint(stage)
            if _last_env_steps(log) > at_checkpoint:
                self.stale[stage] = (_inode(log), at_checkpoint)

    def count(self) -> int:
        total = 0
        for stage in self.stages:
            log = stage / PROGRESS_FILE
            inode, at_checkpoint = self.stale.get(stage, (None, 0))
            total += at_checkpoint if inode is not None and _inode(log) == inode else _last_env_steps(log)
        return total


def _inode(path: Path) -> int | None:
    try:
        return path.stat().st_ino
    except OSError:
        return None


def _steps_at_checkpoint(stage: Path) -> int:
    """`env_steps` logged at the iteration of the stage's newest checkpoint (0 without one)."""
    from opt2skill.rl import checkpoint

    newest = checkpoint.latest(stage)
    if newest is None:
        return 0
    iteration = checkpoint.iteration_of(newest)
    try:
        rows = read_progress(stage)
    except (OSError, ValueError):  # unreadable: the bar starts at 0 rather than stopping the training
        return 0
    return max((int(r["env_steps"]) for r in rows if r["iteration"] <= iteration), default=0)


def _last_env_steps(log: Path) -> int:
    """`env_steps` of a progress log's last complete line; 0 where there is none yet."""
    try:
        with open(log, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - 65536))
            lines = f.read().splitlines()
    except OSError:
        return 0
    for line in reversed(lines):
        try:
            return int(json.loads(line)["env_steps"])
        except (ValueError, KeyError, TypeError):
            continue  # a line being written, or a partial one at the start of the tail
    return 0


def write_provenance(s: Settings, out: Path, steps: Steps, elapsed: float) -> None:
    """Versions, robot hash, settings and every step's status and time, rewritten on every run."""
    import importlib.metadata as md

    from opt2skill.data.atomic import write_json
    from opt2skill.model import load_robot
    from opt2skill.provenance import provenance

    records = {p.stem: json.loads(p.read_text()) for p in sorted(steps.folder.glob("*.json"))}
    extra = {name: md.version(name) for name in ("scipy", "matplotlib", "mink") if _installed(name)}
    write_json(Path(out) / "provenance.json", {
        "experiment": s.experiment, "settings": s.identity(), "workers": getattr(s, "workers", None),
        "provenance": provenance(load_robot("digit").hash, command=f"opt2skill experiment {s.experiment}",
                                 more_libraries=extra),
        "this_invocation_s": elapsed,
        "steps": {name: {"status": r["status"], "elapsed_s": r["elapsed_s"], "finished": r["finished"],
                         "reason": r["result"].get("reason")} for name, r in records.items()},
    })


def _installed(name: str) -> bool:
    import importlib.metadata as md

    try:
        md.version(name)
        return True
    except md.PackageNotFoundError:
        return False


def add_output(outputs: dict[str, Path], steps: Steps, step: str, label: str, field: str) -> None:
    """outputs[label] = the path in field `field` of step `step`'s result, when that step is done."""
    result = done(steps, step)
    if result is not None:
        outputs[label] = Path(result[field])


def publish_table(table: Any, out: Path) -> dict[str, str]:
    """Write a table (its `write(out)` gives the JSON and Markdown paths) and print it."""
    json_path, md_path = table.write(out)
    console.print(table.markdown(), highlight=False, soft_wrap=True)
    return {"json": str(json_path), "table": str(md_path)}
