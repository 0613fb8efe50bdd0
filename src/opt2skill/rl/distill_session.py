"""`opt2skill train --init distill`: distil the optimizer's feedback expert into the actor, then PPO.

One command, two stages, each resumable (docs/distill.md):

    RUN/run.json, RUN/checkpoints/, RUN/progress.jsonl, RUN/tb/   the PPO stage, as a plain run
                                                                 (play, eval, export read it unchanged)
    RUN/distill/stage.json                                       the distillation settings (checked on resume)
    RUN/distill/checkpoints/, RUN/distill/progress.jsonl        the distillation stage
    RUN/tb/distill/                                              its TensorBoard events

1. **Distillation** (`rl.distill.Distiller`) for `distill_steps` environment steps, under the Table II
   conditions the expert tolerates (`distillation_tracking_config`).
2. **PPO** from the distilled actor: the task's randomization and curriculum, the randomization's
   width and the noise rising from about the distillation's (`finetune_tracking_config`), initial
   action noise `finetune_std`; its
   first `critic_warmup_iterations` iterations train the critic only (the actor is frozen, its
   observation normalizer too), so the first policy updates see useful advantages;
   after each PPO update, behaviour-cloning steps toward the expert's labels of PPO's own states
   (`rl.anchor`, `anchor_updates` > 0).

Both stages log to TensorBoard with one step axis, the environment steps since the run began (the
PPO stage's steps continue the distillation's), and wall-clock time continues across the stages in
`elapsed`. A rerun of the same command continues whichever stage was interrupted.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from opt2skill.data.atomic import write_json
from opt2skill.data.record import FRAME_DT
from opt2skill.envs import ReferenceBank, TrackingEnv, tracking_config
from opt2skill.errors import ConfigError, DataError
from opt2skill.expert.acting import EnvExpert
from opt2skill.folder_lock import folder_lock
from opt2skill.output_paths import check_output_dir
from opt2skill.provenance import provenance
from opt2skill.rl import checkpoint, residual
from opt2skill.rl.anchor import ExpertAnchor
from opt2skill.rl.distill import Distiller
from opt2skill.rl.distill_config import DistillConfig, distillation_tracking_config, finetune_tracking_config
from opt2skill.rl.pace import AdaptivePace
from opt2skill.rl.policy import build_actor
from opt2skill.rl.run import RunSpec, check_run, differences, open_run, trim_progress
from opt2skill.rl.best import HeldOutJudge
from opt2skill.rl.config import PPOConfig
from opt2skill.rl import processes
from opt2skill.rl.processes import Group
from opt2skill.rl.session import (TrainRequest, check_checkpoints, group_size, held_out_judge, no_announce,
                                  open_dataset, resume_line, set_threads)
from opt2skill.rl.trainer import Schedule, Trainer

STAGE_DIR = checkpoint.DISTILL_STAGE_DIR
STAGE_FILE = "stage.json"
CHECKPOINT_MINUTES = 1.0  # a kill -9 during distillation loses at most about this much work


class _EnvStepWriter:
    """A TensorBoard writer whose step is a shared counter (environment steps over both stages)."""

    def __init__(self, writer, step):
        self.writer, self.step = writer, step

    def add_scalar(self, tag: str, value: float, _step: int | None = None) -> None:
        self.writer.add_scalar(tag, value, self.step())


def _writer(directory: Path, first_step: int):
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(str(directory), purge_step=first_step + 1, flush_secs=10)


def _open_stage(run: Path, config: DistillConfig, distill_steps: int, group: Group = processes.ONE) -> Path:
    """RUN/distill with its settings recorded (by rank 0); a rerun must bring the same settings."""
    stage = Path(run) / STAGE_DIR
    if not group.is_main:
        group.barrier()  # rank 0 checks and records the stage
        return stage
    identity = {"distill": json.loads(json.dumps(dataclasses.asdict(config))), "distill_steps": distill_steps}
    path = stage / STAGE_FILE
    if path.is_file():
        diff = differences(json.loads(path.read_text()), identity)
        if diff:
            raise ConfigError(f"{run} was distilled with other settings ({'; '.join(diff[:4])}); choose another --out")
    else:
        stage.mkdir(parents=True, exist_ok=True)
        write_json(path, identity)
    group.barrier()
    return stage


def _check_gains(dataset) -> None:
    missing = [i for i in range(len(dataset)) if "gains" not in dataset.meta(i).knot_names]
    if missing:
        raise DataError(f"dataset {dataset.root}: {len(missing)} of {len(dataset)} trajectories have no feedback gains "
                        "(the expert needs them); regenerate it with `opt2skill generate ... --keep-gains`")


def distill_stage(request: TrainRequest, dataset, robot, config, distill: DistillConfig, distill_steps: int,
                  threads: int, progress: bool, announce: Callable[[str], None] = no_announce,
                  judge: HeldOutJudge | None = None, group: Group = processes.ONE) -> tuple[dict[str, Any], int]:
    """Run (or resume) the distillation stage: its final checkpoint's contents and the iteration it
    started from (0 for a fresh stage)."""
    stage = _open_stage(request.out, distill, distill_steps, group)
    batch = group.size * request.num_envs * distill.steps_per_env(FRAME_DT)
    total = -(-distill_steps // batch)
    latest = checkpoint.latest(stage)
    done = checkpoint.load(latest) if latest is not None else None
    if done is not None and done["iteration"] >= total:
        return done, done["iteration"]  # finished before (killed before the PPO stage's first checkpoint)
    env_config = distillation_tracking_config(config, distill)
    bank = ReferenceBank.from_dataset(robot, dataset, env_config.observations.end_effectors)
    with TrackingEnv(robot, bank, env_config, request.num_envs, seed=group.seed(request.seed), threads=threads,
                     device=_device(request, group)) as env:
        torch.manual_seed(request.seed)
        actor = build_actor(distill.student_ppo(), env.actor_dim, env.critic_dim, env.nu)
        expert = dataset_expert(env, dataset, distill)
        distiller = Distiller(env, expert, actor, distill, stage, seed=request.seed, group=group)
        distiller.judge = judge
        if distiller.resume_latest():
            announce(resume_line(request.out, distiller.iteration, checkpoint.latest(stage), "distillation"))
        elif group.is_main:
            trim_progress(stage, 0)
        started = distiller.iteration
        writer = _writer(Path(request.out) / "tb" / STAGE_DIR, distiller.env_steps) if group.is_main else None
        try:
            distiller.train(total, progress=progress,
                            writer=_EnvStepWriter(writer, lambda: distiller.env_steps) if writer else None,
                            checkpoint_every=request.checkpoint_every, checkpoint_minutes=CHECKPOINT_MINUTES)
        finally:
            if writer is not None:
                writer.close()
    group.barrier()  # rank 0 has written the stage's last checkpoint
    return checkpoint.load(checkpoint.latest(stage)), started


def _device(request: TrainRequest, group: Group) -> str:
    """The physics device of this process: process r of a group on `cuda:r` with --device cuda."""
    return f"cuda:{group.local_rank}" if group.size > 1 and request.device == "cuda" else request.device


def set_actor_frozen(trainer: Trainer, frozen: bool) -> None:
    """Freeze the actor for the critic warm-up: no gradients, and its observation normalizer stops
    following the data (eval mode); the critic learns from the actions the distilled actor takes."""
    actor = trainer.alg.actor
    for p in actor.parameters():
        p.requires_grad_(not frozen)
    actor.train(not frozen)


def start_from_distilled(trainer: Trainer, distilled: dict[str, Any]) -> None:
    """Load the distilled actor into PPO (as the frozen base of a residual actor if the trainer's is
    one); give the critic's normalizer statistics of the states the distilled actor visits (one
    rollout's worth of steps), then start new episodes."""
    if trainer.ppo.hidden_dims == residual.hidden_dims(distilled["actor_state_dict"]):
        trainer.alg.actor.load_state_dict(distilled["actor_state_dict"])
    else:
        residual.load_base(trainer.alg.actor, distilled["actor_state_dict"])
    trainer.elapsed = distilled["elapsed"]
    observations = []
    with torch.inference_mode():
        obs = trainer.venv.get_observations()
        for _ in range(trainer.steps_per_env):
            obs, *_ = trainer.venv.step(trainer.alg.actor(obs, stochastic_output=True))
            observations.append(obs)
    trainer.alg.critic.update_normalization(torch.cat(observations))
    trainer.env.reset()
    trainer.venv.refresh()
    trainer.venv.stats.clear()


def dataset_expert(env: TrackingEnv, dataset, distill: DistillConfig) -> EnvExpert:
    """The feedback expert of `env`'s references (the dataset's trajectories, with their gains)."""
    return EnvExpert(env, [dataset[int(p)] for p in env.bank.positions], distill.expert)


def finetune_trainer(env: TrackingEnv, dataset, distill: DistillConfig, run: Path | None, seed: int,
                     group: Group = processes.ONE, ppo: PPOConfig | None = None) -> Trainer:
    """The PPO stage's trainer on `env` (the fine-tuning config's, from `ppo`'s settings), with the
    expert anchor if enabled."""
    trainer = Trainer(env, distill.finetune_ppo(ppo), run, seed=seed, group=group)
    if distill.finetune == "residual":
        residual.freeze_base(trainer.alg.actor, distill.student_ppo().hidden_dims)
    if distill.pace == "adaptive":
        trainer.pace = AdaptivePace(distill.adaptive_step, distill.adaptive_fall_rate)
    if distill.anchor_updates > 0:
        trainer.anchor = ExpertAnchor(dataset_expert(env, dataset, distill), trainer.alg.actor, distill, seed=seed,
                                      group=group)
    return trainer


@dataclass(frozen=True)
class _Prepared:
    """What a distilled training reads and checks before it writes anything."""

    dataset: Any
    robot: Any
    task: Any  # the task's tracking config (the distillation stage's base)
    config: Any  # the PPO stage's, recorded as the run's
    spec: RunSpec
    invocation: dict[str, Any]


def _prepare(request: TrainRequest, distill: DistillConfig, distill_steps: int, size: int,
             check_existing: bool = True) -> _Prepared:
    """As `session.prepare`, for `--init distill`."""
    check_output_dir(request.out)
    dataset, robot = open_dataset(request.dataset)
    _check_gains(dataset)
    task = tracking_config(dataset.identity.get("task", ""), request.ablation, request.history, request.kp_scale,
                           request.sampling, request.base_position, request.rewards, request.noise_min)
    config = finetune_tracking_config(task, distill)
    ppo = distill.finetune_ppo(request.ppo())
    spec = RunSpec(dataset=str(Path(request.dataset).resolve()), dataset_identity=dataset.identity,
                   trajectories=len(dataset), robot=robot.name, robot_hash=robot.hash, tracking=config, ppo=ppo,
                   num_envs=request.num_envs, seed=request.seed,
                   contacts=RunSpec.contacts_of(robot, dataset.meta(0).contact_names), processes=size)
    invocation = {"command": request.command, "steps": request.steps, "init": "distill", "distill_steps": distill_steps,
                  "threads": request.threads_per_process(size),
                  "provenance": provenance(robot.hash, dataset=spec.dataset, seed=request.seed)}
    existing = check_run(request.out, spec) if check_existing else None  # the configuration first, then ...
    if existing and checkpoint.latest(request.out) is not None and not (Path(request.out) / STAGE_DIR).is_dir():
        raise ConfigError(f"{request.out} is a plain PPO run; choose another --out for --init distill")
    return _Prepared(dataset, robot, task, config, spec, invocation)


def train(request: TrainRequest, distill_steps: int = 2_000_000, progress: bool = True,
          distill: DistillConfig | None = None, announce: Callable[[str], None] = no_announce) -> dict[str, Any]:
    """Distil (or resume distilling), then train with PPO (or resume it); the last PPO iteration's
    figures. `announce` is told each stage's resume. With `procs` > 1 both stages run in that many
    processes, started here (or, under torchrun, this is one of them); rank 0's figures are returned."""
    request.check()
    if request.init_from is not None:
        raise ConfigError("--init-from starts PPO from a trained run's checkpoint; --init distill starts from the "
                          "optimizer's expert: give one of them")
    group = processes.from_environment()
    size = group_size(request, group)
    if not (isinstance(distill_steps, int) and distill_steps >= 1):
        raise ConfigError(f"--distill-steps must be a positive number of environment steps, got {distill_steps}")
    distill = distill or DistillConfig()
    distill.check()
    prepared = _prepare(request, distill, distill_steps, size)
    # Both stages are judged under the task's Table II and noise; its errors come before anything starts.
    judge = held_out_judge(request, prepared.dataset, prepared.robot, prepared.task)
    if size > 1 and group.size == 1:
        return processes.launch(size, _train_in_group, request, distill_steps, distill, progress, announce)
    processes.join(group)
    return _train_in_group(request, distill_steps, distill, progress, announce, prepared,
                           judge if group.is_main else None)


def _train_in_group(request: TrainRequest, distill_steps: int, distill: DistillConfig, progress: bool,
                    announce: Callable[[str], None], prepared: _Prepared | None = None,
                    judge: HeldOutJudge | None = None) -> dict[str, Any]:
    """`train` on this process of its group: rank 0 opens and writes the run, every process trains.
    Without `prepared` (a process `launch` started) this process reads and checks for itself."""
    group = processes.from_environment()
    p = prepared
    if p is None:
        p = _prepare(request, distill, distill_steps, group.size, check_existing=group.is_main)
        judge = held_out_judge(request, p.dataset, p.robot, p.task) if group.is_main else None
    if not group.is_main:
        progress, announce = False, no_announce
    # One lock for both stages (RUN/distill is inside RUN), held by rank 0.
    with folder_lock(request.out) if group.is_main else contextlib.nullcontext():
        if group.is_main:
            check_checkpoints(request.out, p.robot, p.config)
            open_run(request.out, p.spec, p.invocation)
        group.barrier()  # the others go on once rank 0 has opened the run
        threads = set_threads(request.threads_per_process(group.size))
        distilled, resumed = None, {"distill": None, "ppo": None}  # the iteration each stage went on from
        if checkpoint.latest(request.out) is None:  # the PPO stage has not started: distil first
            distilled, resumed["distill"] = distill_stage(request, p.dataset, p.robot, p.task, distill, distill_steps,
                                                          threads, progress, announce, judge, group)
        else:
            _open_stage(request.out, distill, distill_steps, group)  # same settings as before
        return _ppo_stage(request, p.dataset, p.robot, p.config, distill, threads, distilled, resumed, progress,
                          announce, judge, group)


def _ppo_stage(request: TrainRequest, dataset, robot, config, distill: DistillConfig, threads: int,
               distilled: dict[str, Any] | None, resumed: dict[str, int | None], progress: bool,
               announce: Callable[[str], None], judge: HeldOutJudge | None = None,
               group: Group = processes.ONE) -> dict[str, Any]:
    """PPO from the distilled actor (`distilled`; None: resume the PPO stage's own checkpoints)."""
    offset = checkpoint.load(checkpoint.latest(Path(request.out) / STAGE_DIR))["env_steps"] if distilled is None \
        else distilled["env_steps"]
    bank = ReferenceBank.from_dataset(robot, dataset, config.observations.end_effectors)
    with TrackingEnv(robot, bank, config, request.num_envs, seed=group.seed(request.seed), threads=threads,
                     device=_device(request, group)) as env:
        trainer = finetune_trainer(env, dataset, distill, request.out, request.seed, group, request.ppo())
        trainer.judge = judge
        if trainer.resume_latest():
            announce(resume_line(request.out, trainer.iteration, checkpoint.latest(request.out), "PPO"))
        else:
            if group.is_main:
                trim_progress(request.out, 0)
            start_from_distilled(trainer, distilled)
        resumed["ppo"] = trainer.iteration
        if trainer.iteration >= trainer.iterations_for(request.steps):
            return {"iteration": trainer.iteration, "env_steps": trainer.env_steps, "already_done": True,
                    "distill_env_steps": offset, "resumed_from": resumed}
        writer = _writer(Path(request.out) / "tb", offset + trainer.env_steps) if group.is_main else None
        logged = _EnvStepWriter(writer, lambda: offset + trainer.env_steps) if writer is not None else None
        schedule = Schedule(request.steps, request.checkpoint_every)
        figures = {}
        try:
            if trainer.iteration < distill.critic_warmup_iterations:
                set_actor_frozen(trainer, True)
                try:
                    figures = trainer.train(schedule, progress=progress, writer=logged,
                                            stop_after=distill.critic_warmup_iterations)
                finally:
                    set_actor_frozen(trainer, False)
            figures = trainer.train(schedule, progress=progress, writer=logged) or figures  # {} if the warm-up ended it
        finally:
            if writer is not None:
                writer.close()
        return {"iteration": trainer.iteration, "env_steps": trainer.env_steps, "elapsed": trainer.elapsed,
                "distill_env_steps": offset, "resumed_from": resumed, "checkpoint": str(checkpoint.latest(request.out)),
                **figures}
