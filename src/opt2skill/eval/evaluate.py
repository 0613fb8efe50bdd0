"""`opt2skill eval` without the command line: a run's policy rolled out on references it did not
train on, every metric of Tables III and IV, success and episode length, as an `EvalReport`.

Rollouts are deterministic (the Gaussian's mean), from each reference's first frame, with the
training task's terminations except the drift one (`eval_config`); randomization and observation
noise are off unless asked for.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from opt2skill.data.reader import Dataset
from opt2skill.envs import evaluation_config, layout
from opt2skill.envs.config import TrackingConfig
from opt2skill.errors import ConfigError, DataError
from opt2skill.eval.references import ReferenceSet, check_metric_fields, position_fingerprint, select_references
from opt2skill.eval.report import EvalReport, TrajectoryResult, read_report
from opt2skill.eval.rollout import Rollout, planned_steps, rollout
from opt2skill.eval.task_metrics import task_metrics
from opt2skill.model import load_robot
from opt2skill.model.robot import Robot
from opt2skill.provenance import provenance
from opt2skill.rl import checkpoint as checkpoints
from opt2skill.rl.policy import Policy, load_policy
from opt2skill.rl.run import RunSpec, read_spec


@dataclass(frozen=True)
class EvalRequest:
    run: Path
    dataset: Path | None = None  # default: the run's training dataset
    n: int = 20
    split: str = "held-out"
    indices: tuple[int, ...] = ()  # generation indices instead of a split
    randomize: bool = False  # Table II randomization on
    noise: bool = False  # Table II observation noise on
    pushes: bool = False  # the training's pushes on (Section III-B's external disturbances; not Table II)
    seed: int = 0
    checkpoint: Path | None = None  # default: the run's newest
    threads: int | None = None

    def options(self) -> dict[str, Any]:
        # "pushes" only when on: the reports written before it keep their keys (and their reuse)
        return {"randomize": self.randomize, "noise": self.noise, **({"pushes": True} if self.pushes else {}),
                "seed": self.seed}

    def default_out(self, spec: RunSpec) -> Path:
        name = Path(self.dataset or spec.dataset).name
        parts = [name, self.split if not self.indices else "given"]
        parts += [p for p, on in (("randomized", self.randomize), ("noise", self.noise), ("pushes", self.pushes)) if on]
        parts += [f"seed{self.seed}"] if self.seed else []
        return Path(self.run) / "eval" / "-".join(parts)


@dataclass
class RunPolicy:
    policy: Policy
    spec: RunSpec
    robot: Robot
    info: dict[str, Any]  # EvalReport.policy


def load_run_policy(run: Path, checkpoint: Path | None = None) -> RunPolicy:
    """The run's policy (newest checkpoint unless given), checked against the installed robot and the
    run's observation layout."""
    run = Path(run)
    spec = read_spec(run)
    robot = load_robot(spec.robot)
    if robot.hash != spec.robot_hash:
        raise DataError(f"run {run} was trained on a different '{spec.robot}' robot file (hash {spec.robot_hash[:12]}); "
                        f"the installed one has hash {robot.hash[:12]}")
    path = Path(checkpoint) if checkpoint else checkpoints.policy_default(run)
    if path is None:
        raise DataError(f"run {run} has no checkpoint yet")
    ppo_dir, distill_dir = checkpoints.policy_checkpoint_dirs(run)
    best_dir, final_dir = checkpoints.best_path(run).parent, checkpoints.final_path(run).parent
    if path.resolve().parent not in (ppo_dir.resolve(), distill_dir.resolve(), best_dir.resolve(), final_dir.resolve()):
        # A checkpoint carries no task or robot: only its own run says what it was trained for.
        raise DataError(f"checkpoint {path} is not one of run {run}'s ({ppo_dir}, {distill_dir} for the "
                        f"distillation stage, {best_dir} or {final_dir}); evaluate the run it belongs to")
    policy, _ = load_policy(run, path)
    expected = layout(spec.tracking.observations, robot.nu, len(spec.contact_names(robot))).actor_dim
    if policy.obs_dim != expected:
        raise DataError(f"checkpoint {path} takes {policy.obs_dim} observations; run {run}'s task gives {expected} "
                        "(a checkpoint of another run or configuration)")
    t = spec.tracking
    stage = {distill_dir.resolve(): "distillation ", best_dir.resolve(): "best: ",
             final_dir.resolve(): "final: "}.get(path.resolve().parent, "")
    name = f"{run.name} ({stage}iteration {policy.iteration})"
    info = {
        "name": name, "run": str(run.resolve()), "checkpoint": str(path.resolve()), "iteration": policy.iteration,
        "env_steps": policy.env_steps, "robot": spec.robot, "robot_hash": spec.robot_hash, "task": t.task, "ablation": t.ablation, "history": t.observations.history,
        "key": {"checkpoint": str(path.resolve()), "iteration": policy.iteration, "env_steps": policy.env_steps},
        "description": f"run {run.resolve()}, checkpoint {path.name} (iteration {policy.iteration}, "
                       f"{policy.env_steps:,} env steps), {t.task}, {t.ablation}, history {t.observations.history}",
    }
    return RunPolicy(policy, spec, robot, info)


def training_fingerprints(spec: RunSpec, run: Path | None = None) -> list[str] | None:
    """Fingerprints of the references a run trained on: its dataset's first `spec.trajectories`
    accepted trajectories, or, when that dataset is gone or was changed since, those the run
    directory records (a shipped policy's, `opt2skill.pretrained`); None when neither is there. A
    file that has gone bad since is left out: only a reference with its very parameters could be
    misjudged."""
    try:
        dataset = Dataset.open(spec.dataset)
    except DataError:
        dataset = None
    if dataset is None or dataset.identity != spec.dataset_identity or len(dataset) < spec.trajectories:
        return recorded_fingerprints(run)
    return [position_fingerprint(dataset, p) for p in dataset.sound(range(spec.trajectories))]


def recorded_fingerprints(run: Path | None) -> list[str] | None:
    from opt2skill.pretrained import FINGERPRINTS

    path = Path(run) / FINGERPRINTS if run is not None else None
    if path is None or not path.is_file():
        return None
    try:
        return list(json.loads(path.read_text())["fingerprints"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{path} is unreadable ({exc})") from None


def open_references(request: EvalRequest, run: RunPolicy) -> tuple[Dataset, ReferenceSet]:
    dataset = Dataset.open(request.dataset or run.spec.dataset)
    if dataset.identity.get("robot_hash") not in (None, run.robot.hash):
        raise DataError(f"dataset {dataset.root} was made for another '{dataset.identity.get('robot')}' robot file "
                        f"than run {request.run} (hash {str(dataset.identity.get('robot_hash'))[:12]})")
    refs = select_references(dataset, training_fingerprints(run.spec, run.info["run"]), request.n, request.split,
                             list(request.indices), what=f"run {request.run}")
    check_metric_fields(dataset, run.spec.tracking.task, refs.positions[0], run.spec.contact_names(run.robot))
    return dataset, refs


def evaluate(request: EvalRequest, progress: bool = True, reuse: Path | None = None,
             run: RunPolicy | None = None) -> tuple[EvalReport, list[Rollout] | None]:
    """Roll the run's policy out on the chosen references and measure. With `reuse` (a report file),
    a report with the same key (checkpoint, references, options) is returned without rollouts."""
    if request.n < 1:
        raise ConfigError(f"--n must be >= 1, got {request.n}")
    run = run or load_run_policy(request.run, request.checkpoint)
    dataset, refs = open_references(request, run)
    report = EvalReport("eval", run.info, refs.to_dict(), request.options(), [])
    if reuse is not None and Path(reuse).is_file():
        try:
            cached = read_report(reuse)
        except DataError:
            cached = None
        if cached is not None and cached.key() == report.key():
            return cached, None
    start = time.perf_counter()
    threads = request.threads or os.cpu_count() or 1
    torch.set_num_threads(threads)
    references = [dataset[p] for p in refs.positions]
    config = eval_config(run.spec.tracking, request.randomize, request.noise, request.pushes)
    with step_bar(references, progress, "evaluating") as bar:
        rollouts = rollout(run.robot, references, run.policy, config, seed=request.seed, threads=threads,
                           progress=bar.update)
    report.results = [result_of(r, index, seen) for r, index, seen in zip(rollouts, refs.indices, refs.seen)]
    report.elapsed = time.perf_counter() - start
    report.provenance = provenance(run.robot.hash, command="eval", run=run.info["run"])
    return report, rollouts


def eval_config(tracking: TrackingConfig, randomize: bool = False, noise: bool = False,
                pushes: bool = False) -> TrackingConfig:
    """The training task for evaluation (`envs.evaluation_config`), with one change: drifting from the
    reference does not end an episode (`max_xy_error` off). Drift is what E_pos-x and E_pos-y
    measure over the whole reference; falls, height and orientation losses still end it."""
    config = evaluation_config(tracking, randomize=randomize, noise=noise, pushes=pushes)
    return dataclasses.replace(config, terminations=dataclasses.replace(config.terminations, max_xy_error=0.0))


def result_of(r: Rollout, index: int, seen: bool | None) -> TrajectoryResult:
    return TrajectoryResult(index, r.reference.params, seen, r.cause, r.tracked.num_frames, r.reference.num_frames,
                            r.errors(), task_metrics(r.reference, r.tracked))


def step_bar(references, enabled: bool, desc: str):
    """A progress bar over policy steps of all references (world-steps), with an ETA."""
    from tqdm import tqdm

    return tqdm(total=planned_steps(references), disable=not enabled, unit="step", unit_scale=True, desc=desc, dynamic_ncols=True,
                leave=False)
