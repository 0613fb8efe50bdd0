"""`opt2skill train` and `opt2skill play` without the command line: checked requests, the run
directory, the environment, the trainer; resumable and logged (docs/training.md)."""

from __future__ import annotations

import contextlib
import hashlib
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from opt2skill.data.reader import Dataset
from opt2skill.envs import ABLATIONS, ReferenceBank, TrackingEnv, evaluation_config, tracking_config
from opt2skill.envs.config import (BASE_POSITION, SAMPLINGS, RewardConfig, TrackingConfig, check_reference_inputs,
                                  with_rewards)
from opt2skill.envs.evaluation import TrackedMotion, track
from opt2skill.errors import ConfigError, DataError
from opt2skill.eval.references import check_contacts
from opt2skill.folder_lock import folder_lock
from opt2skill.model import load_robot
from opt2skill.output_paths import check_output_dir
from opt2skill.provenance import provenance
from opt2skill.rl import checkpoint
from opt2skill.rl.best import HeldOutJudge, JudgeConfig
from opt2skill.rl.config import PPOConfig
from opt2skill.rl import processes
from opt2skill.rl.policy import Policy, load_policy
from opt2skill.rl.processes import Group
from opt2skill.rl.run import RunSpec, check_run, open_run, trim_progress
from opt2skill.rl.trainer import Schedule, Trainer
from opt2skill.sim.devices import check_device

MAX_ENVS = 4096
MAX_PROCS = 64


@dataclass(frozen=True)
class TrainRequest:
    dataset: Path
    out: Path
    steps: int = 10_000_000  # environment steps, all worlds together
    num_envs: int = 128
    history: int = 10
    ablation: str = "pos_f_t"
    seed: int = 0
    threads: int | None = None  # physics and torch threads; None: every core
    checkpoint_every: int = 50  # iterations
    command: str = ""
    kp_scale: float = 1.0  # servo stiffness for this policy (envs.config.ActionConfig.kp_scale)
    held_out: Path | None = None  # references of another seed: judge the actor on them, keep the best (rl.best)
    judge: JudgeConfig = JudgeConfig()
    device: str = "cpu"  # physics backend: cpu (C MuJoCo) or cuda (MuJoCo Warp), opt2skill.sim.devices
    sampling: str = "uniform"  # where episodes start: uniform or adaptive (envs.start_sampling)
    procs: int = 1  # processes training together (rl.processes), each with num_envs worlds of its own
    mixed_precision: bool = False  # bf16 autocast in PPO's update (rl.config.PPOConfig.mixed_precision)
    base_position: str = "task"  # the base-position reward: as the task registers it, on or off (envs.config)
    # A run (its newest checkpoint) or a checkpoint file to start PPO from: a fine-tune (`init_source`)
    init_from: Path | None = None
    # Reward terms changed from Table I: (name, weight, scale or None), envs.config.with_rewards
    rewards: tuple[tuple[str, float, float | None], ...] = ()
    # The least share of Table II's observation noise a world trains with (envs.config.NoiseConfig)
    noise_min: float = 1.0

    def check(self) -> None:
        if not (isinstance(self.steps, int) and self.steps >= 1):
            raise ConfigError(f"--steps must be a positive number of environment steps, got {self.steps}")
        if not (1 <= self.num_envs <= MAX_ENVS):
            raise ConfigError(f"--num-envs must be in [1, {MAX_ENVS}], got {self.num_envs}")
        if not (0 <= self.history <= 50):
            raise ConfigError(f"--history must be in [0, 50] samples, got {self.history}")
        if self.ablation not in ABLATIONS:
            raise ConfigError(f"--ablation must be one of {', '.join(ABLATIONS)}, got '{self.ablation}'")
        if not 0.05 <= self.kp_scale <= 2:
            raise ConfigError(f"--kp-scale must be in [0.05, 2], got {self.kp_scale}")
        if self.seed < 0:
            raise ConfigError(f"--seed must be >= 0, got {self.seed}")
        if self.threads is not None and self.threads < 1:
            raise ConfigError(f"--threads must be >= 1, got {self.threads}")
        if self.checkpoint_every < 1:
            raise ConfigError(f"--checkpoint-every must be >= 1 iteration, got {self.checkpoint_every}")
        self.judge.check()
        if self.sampling not in SAMPLINGS:
            raise ConfigError(f"--sampling must be one of {', '.join(SAMPLINGS)}, got '{self.sampling}'")
        check_device(self.device)  # e.g. --device cuda without a GPU: one error before anything is written
        if not (isinstance(self.procs, int) and 1 <= self.procs <= MAX_PROCS):
            raise ConfigError(f"--procs must be in [1, {MAX_PROCS}] processes, got {self.procs}")
        if self.base_position not in BASE_POSITION:
            raise ConfigError(f"--base-position must be one of {', '.join(BASE_POSITION)}, got '{self.base_position}'")
        if not 0 <= self.noise_min <= 1:
            raise ConfigError(f"--noise-min must be a share in [0, 1] of Table II's observation noise, got {self.noise_min}")
        force, torque = ABLATIONS[self.ablation]
        with_rewards(RewardConfig(), self.rewards, force, torque)  # names, signs and inputs, before any reading

    def ppo(self) -> PPOConfig:
        """The PPO settings this request changes from the defaults (a distilled run's PPO stage starts from them)."""
        return PPOConfig(mixed_precision=self.mixed_precision)

    def threads_per_process(self, size: int) -> int:
        """--threads, or this machine's cores shared out among the group's processes on it."""
        return self.threads or max(1, (os.cpu_count() or 1) // size)


def group_size(request: TrainRequest, group: Group) -> int:
    """How many processes train: torchrun's (if started by it), else --procs."""
    if group.size > 1 and request.procs not in (1, group.size):
        raise ConfigError(f"--procs {request.procs} differs from the {group.size} processes torchrun started; "
                          f"leave --procs out under torchrun")
    return group.size if group.size > 1 else request.procs


def open_dataset(path: Path):
    """The dataset at `path` and the robot it was made for (checked: accepted trajectories, robot file)."""
    dataset = Dataset.open(path)
    if len(dataset) == 0:
        raise DataError(f"dataset {path} has no accepted trajectories to train on")
    robot = load_robot(dataset.identity.get("robot", "digit"))
    if dataset.identity.get("robot_hash") != robot.hash:
        raise DataError(f"dataset {path} was made with a different '{robot.name}' robot file "
                        f"(hash {str(dataset.identity.get('robot_hash'))[:12]}, installed {robot.hash[:12]})")
    dataset.check()  # training reads every file: name every bad one now, at once
    return dataset, robot


def held_out_judge(request: TrainRequest, dataset, robot, tracking: TrackingConfig) -> HeldOutJudge | None:
    """The judge of `request.held_out` (None without one): its first `judge.n` references, which must be
    the training task's, for the same robot, and not the training dataset itself."""
    if request.held_out is None:
        return None
    held_out, held_robot = open_dataset(request.held_out)
    if held_robot.hash != robot.hash or held_out.identity.get("task") != dataset.identity.get("task"):
        raise DataError(f"--held-out {request.held_out} holds '{held_out.identity.get('task')}' references of "
                        f"robot '{held_robot.name}'; training is on '{dataset.identity.get('task')}' of '{robot.name}'")
    if Path(request.held_out).resolve() == Path(request.dataset).resolve():
        raise ConfigError("--held-out must be references the run does not train on (another seed), not --dataset")
    check_contacts(held_out.meta(0).contact_names, dataset.meta(0).contact_names, f"--held-out {request.held_out}")
    references = [held_out[i] for i in range(min(request.judge.n, len(held_out)))]
    return HeldOutJudge(request.out, robot, references, tracking, request.judge, threads=request.threads)


def check_checkpoints(run: Path, robot, config) -> None:
    """A run's newest checkpoints (its own and its distillation stage's) must be for this robot and
    task: checked before a resume writes anything into the run."""
    obs = config.observations
    expected = checkpoint.identity(robot.name, robot.hash, config.task, config.ablation, obs.history, obs.stride)
    for directory in (Path(run), Path(run) / checkpoint.DISTILL_STAGE_DIR):
        path = checkpoint.latest(directory)
        if path is not None:
            checkpoint.check_identity(path, checkpoint.load(path), expected)


def init_source(path: Path, robot, config: TrackingConfig) -> dict[str, Any]:
    """The checkpoint a fine-tune starts from: `path` itself, or the newest of the run `path`; checked
    to hold a policy of this robot and task with the same inputs (reads only). Its path, iteration
    and sha256 go into the new run's identity."""
    path = Path(path)
    if path.is_dir():
        found = checkpoint.latest(path)
        if found is None:
            raise DataError(f"--init-from {path} has no checkpoint to start from (a run directory with "
                            "checkpoints/model_*.pt, or a checkpoint file); a shipped policy "
                            "holds its actor alone and cannot be fine-tuned")
        path = found
    elif not path.is_file():
        raise DataError(f"--init-from {path} does not exist (give a run directory or one of its checkpoint files)")
    data = checkpoint.load(path)
    obs = config.observations
    checkpoint.check_identity(path, data, checkpoint.identity(robot.name, robot.hash, config.task, config.ablation,
                                                              obs.history, obs.stride))
    if "identity" not in data or "alg" not in data:
        raise DataError(f"--init-from {path} is not a PPO checkpoint of a run (no identity or networks)")
    return {"checkpoint": str(path.resolve()), "iteration": int(data["iteration"]),
            "sha256": hashlib.sha256(path.read_bytes()).hexdigest()}


def set_threads(threads: int | None) -> int:
    """Torch threads = physics threads = cores: collection and learning alternate, so they never
    compete (docs/training.md)."""
    n = threads or os.cpu_count() or 1
    torch.set_num_threads(n)
    return n


def no_announce(line: str) -> None:
    """The default `announce`: library callers that want no output."""


def resume_line(run: Path, iteration: int, path: Path | None, stage: str = "") -> str:
    return f"resuming {run}{' (' + stage + ')' if stage else ''} from iteration {iteration} (checkpoint {path})"


@dataclass(frozen=True)
class Prepared:
    """What a training reads and checks before it writes anything."""

    dataset: Any
    robot: Any
    config: TrackingConfig
    ppo: PPOConfig
    spec: RunSpec
    invocation: dict[str, Any]


def prepare(request: TrainRequest, size: int, check_existing: bool = True) -> Prepared:
    """The dataset, robot, task and run identity of `request` trained by `size` processes; checked
    against an existing run (reads only) unless `check_existing` is False (the processes of a group
    other than rank 0, which may be writing the run already)."""
    check_output_dir(request.out)
    dataset, robot = open_dataset(request.dataset)
    if len(dataset):  # kinematic references (IK, human) and force/torque inputs: refused before any work
        first = dataset.meta(0)
        check_reference_inputs(request.ablation, first.has_dynamics, first.source)
    config = tracking_config(dataset.identity.get("task", ""), request.ablation, request.history, request.kp_scale,
                             request.sampling, request.base_position, request.rewards, request.noise_min)
    ppo = request.ppo()
    source = init_source(request.init_from, robot, config) if request.init_from is not None else None
    spec = RunSpec(dataset=str(Path(request.dataset).resolve()), dataset_identity=dataset.identity,
                   trajectories=len(dataset), robot=robot.name, robot_hash=robot.hash, tracking=config, ppo=ppo,
                   num_envs=request.num_envs, seed=request.seed,
                   contacts=RunSpec.contacts_of(robot, dataset.meta(0).contact_names), processes=size,
                   init_from=source)
    invocation = {"command": request.command, "steps": request.steps, "threads": request.threads_per_process(size),
                  "provenance": provenance(robot.hash, dataset=spec.dataset, seed=request.seed)}
    if check_existing:
        check_run(request.out, spec)  # a resume with another configuration: said before the slow loading
    return Prepared(dataset, robot, config, ppo, spec, invocation)


def train(request: TrainRequest, progress: bool = True, announce: Callable[[str], None] = no_announce) -> dict[str, Any]:
    """Train (or resume) the run `request.out`; the last iteration's figures. `announce` is told a
    resume (the line `resume_line` makes). With `procs` > 1 the processes are started here (or, under
    torchrun, this is one of them): rank 0's figures are returned."""
    request.check()
    group = processes.from_environment()
    size = group_size(request, group)
    prepared = prepare(request, size)
    judge = held_out_judge(request, prepared.dataset, prepared.robot, prepared.config)  # its errors before anything starts
    if size > 1 and group.size == 1:
        return processes.launch(size, _train_in_group, request, progress, announce)
    processes.join(group)
    return _train_in_group(request, progress, announce, prepared, judge if group.is_main else None)


def _train_in_group(request: TrainRequest, progress: bool, announce: Callable[[str], None],
                    prepared: Prepared | None = None, judge: HeldOutJudge | None = None) -> dict[str, Any]:
    """`train` on this process of its group: rank 0 opens and writes the run, every process trains.
    Without `prepared` (a process `launch` started) this process reads and checks for itself."""
    group = processes.from_environment()
    if prepared is None:
        prepared = prepare(request, group.size, check_existing=group.is_main)
        judge = held_out_judge(request, prepared.dataset, prepared.robot, prepared.config) if group.is_main else None
    bank = ReferenceBank.from_dataset(prepared.robot, prepared.dataset, prepared.config.observations.end_effectors)
    with folder_lock(request.out) if group.is_main else contextlib.nullcontext():
        existed = None
        if group.is_main:
            check_checkpoints(request.out, prepared.robot, prepared.config)
            existed = open_run(request.out, prepared.spec, prepared.invocation)
        existed = group.decide(existed)  # the others wait here until rank 0 has opened the run
        if not group.is_main:
            progress, announce = False, no_announce
        return _train_ppo(request, prepared.robot, bank, prepared.config, prepared.ppo, existed, progress, announce,
                          judge, group, prepared.spec.init_from)


def _train_ppo(request: TrainRequest, robot, bank, config, ppo: PPOConfig, existed: bool, progress: bool,
               announce: Callable[[str], None], judge: HeldOutJudge | None = None,
               group: Group = processes.ONE, source: dict[str, Any] | None = None) -> dict[str, Any]:
    """The PPO loop of `train` on an opened run (its lock held by rank 0); a new run starts from the
    checkpoint `source` (`init_source`) when given."""
    from torch.utils.tensorboard import SummaryWriter

    threads = set_threads(request.threads_per_process(group.size))
    device = f"cuda:{group.local_rank}" if group.size > 1 and request.device == "cuda" else request.device
    with TrackingEnv(robot, bank, config, request.num_envs, seed=group.seed(request.seed), threads=threads,
                     device=device) as env:
        trainer = Trainer(env, ppo, request.out, seed=request.seed, group=group)
        trainer.judge = judge
        if existed and trainer.resume_latest():
            announce(resume_line(request.out, trainer.iteration, checkpoint.latest(request.out)))
        else:
            if group.is_main:
                trim_progress(request.out, 0)
            if source is not None:
                path = Path(source["checkpoint"])
                trainer.start_from(checkpoint.load(path), path)
                announce(f"starting {request.out} from {path} (iteration {source['iteration']}), the curriculum "
                         f"where that run left it ({trainer.curriculum_start:.0%})")
            else:
                trainer.warm_up_normalizers()
        if trainer.iteration >= trainer.iterations_for(request.steps):
            return {"iteration": trainer.iteration, "env_steps": trainer.env_steps, "already_done": True}
        writer = None
        if group.is_main:
            writer = SummaryWriter(str(Path(request.out) / "tb"), purge_step=trainer.iteration + 1, flush_secs=10)
        try:
            figures = trainer.train(Schedule(request.steps, request.checkpoint_every), progress=progress, writer=writer)
        finally:
            if writer is not None:
                writer.close()
        return {"iteration": trainer.iteration, "env_steps": trainer.env_steps, "elapsed": trainer.elapsed,
                "checkpoint": str(checkpoint.latest(request.out)), **figures}


@dataclass
class PlayResult:
    policy: Policy
    spec: RunSpec
    motions: list[TrackedMotion]
    errors: list[dict[str, float]]  # eval.metrics tracking errors per motion


def play(run: Path, n: int = 4, randomize: bool = False, noise: bool = False, seed: int = 0,
         dataset: Path | None = None) -> PlayResult:
    """Roll the run's policy (its best checkpoint if it kept one, else the newest) out on the first `n`
    references of its dataset (or of `dataset`) from frame 0, deterministic actions, randomization and
    noise off unless asked."""
    from opt2skill.eval.metrics import tracking_errors

    if n < 1:
        raise ConfigError(f"--n must be >= 1, got {n}")
    path = checkpoint.policy_default(run)
    policy, spec = load_policy(run, path)
    references, robot = open_dataset(Path(dataset or spec.dataset))
    if dataset is None and references.identity != spec.dataset_identity:
        raise DataError(f"the dataset at {spec.dataset} is no longer the one run {run} was trained on")
    if references.identity.get("task") != spec.tracking.task or robot.hash != spec.robot_hash:
        raise DataError(f"dataset {references.root} holds '{references.identity.get('task')}' references of robot "
                        f"'{robot.name}'; the policy tracks '{spec.tracking.task}' on '{spec.robot}'")
    n = min(n, len(references))
    subset = np.arange(n)
    config = evaluation_config(spec.tracking, randomize=randomize, noise=noise)
    bank = ReferenceBank.from_dataset(robot, references, config.observations.end_effectors, subset=subset)
    set_threads(None)
    with TrackingEnv(robot, bank, config, n, seed=seed) as env:
        env.set_progress(1.0)
        motions = track(env, policy, np.arange(n))
    errors = []
    for motion in motions:
        reference = references[motion.position]
        errors.append(tracking_errors(reference, motion.record(robot, reference), fell=motion.fell).as_dict())
    return PlayResult(policy, spec, motions, errors)
