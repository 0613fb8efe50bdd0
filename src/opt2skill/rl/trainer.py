"""PPO training of a tracking policy: rsl_rl's PPO, our loop (progress bar, logs, checkpoints, resume).

rsl_rl supplies the algorithm (PPO with the adaptive learning rate), the models (MLPs with
observation normalization, Gaussian actions) and the rollout storage. The loop is ours because a
run here must show a progress bar with an ETA, tell the environment the training progress (the
noise curriculum), write checkpoints atomically with the random generators and resume from them,
and log every reward term: rsl_rl's `OnPolicyRunner` prints a page per iteration and saves without
those. Its loop is the same sequence of `act`, `process_env_step`, `compute_returns`, `update`.
"""

from __future__ import annotations

import contextlib
import io
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from rsl_rl.algorithms import PPO

from opt2skill.data.atomic import dumps
from opt2skill.envs import TrackingEnv
from opt2skill.errors import DataError
from opt2skill.rl import checkpoint, processes
from opt2skill.rl.best import judge_actor
from opt2skill.rl.config import PPOConfig
from opt2skill.rl.processes import ONE, Group
from opt2skill.rl.run import PROGRESS_FILE, trim_progress
from opt2skill.rl.vec_env import TrackingVecEnv
from opt2skill.sim.devices import learner_device


@dataclass(frozen=True)
class Schedule:
    """How long and how often: environment steps (all worlds), checkpoint cadence."""

    total_steps: int
    checkpoint_every: int = 50  # iterations
    checkpoint_minutes: float = 5.0  # also checkpoint when this much wall time has passed


def build_algorithm(venv: TrackingVecEnv, ppo: PPOConfig, group: Group = ONE) -> PPO:
    """rsl_rl's PPO with our actor and critic settings (its construction chatter kept off the terminal);
    in a group of processes, averaging gradients with the others and starting from rank 0's networks."""
    cfg = {**ppo.rsl_rl(venv.env.sim.policy_dt), "multi_gpu": group.rsl_rl()}
    with contextlib.redirect_stdout(io.StringIO()):
        alg = PPO.construct_algorithm(venv.get_observations(), venv, cfg, str(venv.device))
    last = [m for m in alg.actor.mlp if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():  # the untrained policy's mean action is ~0: the default pose, not a random offset
        last.weight.mul_(ppo.actor_output_gain)
        last.bias.zero_()
    if group.size > 1:
        alg.broadcast_parameters()
    return alg


class Trainer:
    def __init__(self, env: TrackingEnv, ppo: PPOConfig, run: Path | None = None, seed: int = 0, group: Group = ONE):
        """`group`: one of several processes training together (`rl.processes`); `env` is this
        process's worlds, `run` is written by rank 0 only, and the counters and schedule are the group's."""
        self.env, self.ppo, self.run = env, ppo, (Path(run) if run is not None else None)
        self.group, self.seed = group, seed
        # Optional `rl.anchor.ExpertAnchor` on this trainer's actor (set before resuming): told each actor
        # observation before the action (`observe`), trained after each PPO update (`learn`).
        self.anchor = None
        # Optional `rl.best.HeldOutJudge`: judges the actor on held-out references every `every`
        # iterations and at the end, keeping the best checkpoint.
        self.judge = None
        # Optional `rl.pace.AdaptivePace`: the curriculum advances with the policy's failure rate
        # instead of with the environment steps.
        self.pace = None
        # Where the curriculum starts: 0 for a fresh policy; a fine-tune (`start_from`) starts where its
        # source run left it and moves from there to the end over its own steps.
        self.curriculum_start = 0.0
        torch.manual_seed(seed)  # the networks' initialization: the same on every process of a group
        self.venv = TrackingVecEnv(env, ppo.reward_scale or None, learner_device(env.device, group.size))
        self.alg = build_algorithm(self.venv, ppo, group)
        if not group.is_main:  # the actions' noise: a stream of each process's own (rank 0's goes on as one process's)
            torch.manual_seed(group.seed(seed))
        self.steps_per_env = ppo.steps_per_env(env.sim.policy_dt)
        self.local_batch = env.num_envs * self.steps_per_env
        self.batch = group.size * self.local_batch  # environment steps per iteration, all processes
        self.iteration = 0  # completed iterations
        self.env_steps = 0
        self.elapsed = 0.0  # wall seconds spent training, over all invocations

    # ------------------------------------------------------------ checkpoints

    def state(self) -> dict[str, Any]:
        return {
            "alg": self.alg.save(),
            "learning_rate": self.alg.learning_rate,
            "env_steps": self.env_steps,
            "elapsed": self.elapsed,
            "progress": self.env.progress,
            "curriculum_start": self.curriculum_start,
            "torch_rng": torch.get_rng_state(),
            # the actions' noise is drawn on the learner's device: a GPU's generator resumes too
            **({"cuda_rng": torch.cuda.get_rng_state(self.venv.device)} if self.venv.device.type == "cuda" else {}),
            "env_rng": self.env.rng.bit_generator.state,
            "starts": self.env.starts.state(),
            "dims": self.dims(),
            "identity": self.identity(),
            **({"anchor": self.anchor.state()} if self.anchor is not None else {}),
            **({"pace": self.pace.state()} if self.pace is not None else {}),
        }

    def dims(self) -> dict[str, int]:
        return {"actor": self.env.actor_dim, "critic": self.env.critic_dim, "actions": self.env.nu}

    def identity(self) -> dict[str, Any]:
        env = self.env
        obs = env.config.observations
        return checkpoint.identity(env.robot.name, env.robot.hash, env.config.task, env.config.ablation, obs.history,
                                   obs.stride)

    def save(self) -> Path:
        return checkpoint.save(self.run, self.iteration, self.state())

    def restore(self, data: dict[str, Any], path: Path | str = "checkpoint") -> None:
        """Continue from a checkpoint: models, optimizer, learning rate, counters, curriculum, RNGs.
        The worlds start new episodes (the episodes in flight at the kill are not in the checkpoint)."""
        checkpoint.check_identity(Path(path), data, self.identity())
        self._load_networks(data)
        self.iteration, self.env_steps, self.elapsed = data["iteration"], data["env_steps"], data["elapsed"]
        torch.set_rng_state(data["torch_rng"])
        if self.venv.device.type == "cuda" and "cuda_rng" in data:
            torch.cuda.set_rng_state(data["cuda_rng"], self.venv.device)
        if self.anchor is not None and "anchor" in data:
            self.anchor.restore(data["anchor"])
        if self.pace is not None and "pace" in data:
            self.pace.restore(data["pace"])
        self.env.rng.bit_generator.state = data["env_rng"]
        if "starts" in data:
            self.env.starts.restore(data["starts"])
        if not self.group.is_main:  # the checkpoint holds rank 0's streams: the others draw fresh ones of their own
            seed = self.group.seed(self.seed) + self.iteration
            torch.manual_seed(seed)
            self.env.rng.bit_generator.state = np.random.default_rng(seed).bit_generator.state
        self.curriculum_start = data.get("curriculum_start", 0.0)
        self.env.set_progress(data["progress"])
        self.env.reset()
        self.venv.refresh()

    def start_from(self, data: dict[str, Any], path: Path | str = "checkpoint") -> None:
        """Begin a fine-tune from another run's checkpoint: its actor (observation normalizer and action
        noise included), critic, optimizer and learning rate, and its curriculum progress as the start
        of this run's. The counters and random streams stay this run's own."""
        checkpoint.check_identity(Path(path), data, self.identity())
        if data.get("dims", self.dims()) != self.dims():
            raise DataError(f"{path} holds networks for {data['dims']} observations and actions; this run's task gives "
                            f"{self.dims()} (another scene or contacts): fine-tune a run of the same inputs")
        self._load_networks(data)
        self.curriculum_start = float(data["progress"])
        self.env.set_progress(self.curriculum_start)
        self.env.reset()
        self.venv.refresh()

    def _load_networks(self, data: dict[str, Any]) -> None:
        """Actor, critic, optimizer (rsl_rl's `PPO.load`) and the learning rate of a checkpoint."""
        self.alg.load(data["alg"], {"actor": True, "critic": True, "optimizer": True}, strict=True)
        self.alg.learning_rate = data["learning_rate"]
        for group in self.alg.optimizer.param_groups:
            group["lr"] = data["learning_rate"]

    def resume_latest(self) -> bool:
        path = checkpoint.latest(self.run)
        if path is None:
            return False
        self.restore(checkpoint.load(path), path)
        if self.group.is_main:
            trim_progress(self.run, self.iteration)
        return True

    # ------------------------------------------------------------ training

    def warm_up_normalizers(self) -> None:
        """Give the observation normalizers statistics before the first rollout.

        rsl_rl updates them after each PPO update, so the first rollout would feed raw observations
        (contact forces in hundreds of newtons, gains in hundreds) to the fresh networks, and the
        action history would then feed the resulting wild actions back. One rollout's worth of steps
        with actions drawn like the initial policy's (mean 0, its initial std) gives statistics of
        the states the first rollout will see; the worlds then start new episodes.
        """
        observations = []
        std = self.ppo.init_std
        with torch.no_grad():
            for _ in range(self.steps_per_env):
                obs, *_ = self.venv.step(std * torch.randn(self.env.num_envs, self.env.nu, device=self.venv.device))
                observations.append(obs)
            batch = torch.cat(observations)
            self.alg.actor.update_normalization(batch)
            self.alg.critic.update_normalization(batch)
        self.env.reset()
        self.venv.refresh()
        self.venv.stats.clear()

    def iterations_for(self, total_steps: int) -> int:
        return math.ceil(total_steps / self.batch)

    def train_iteration(self) -> dict[str, float]:
        """Collect one rollout of every world, update the policy; the iteration's figures."""
        return self._learn(*self._collect())

    def _collect(self) -> tuple[float, float]:
        """One rollout of every world into PPO's storage; when it started and ended."""
        alg, venv = self.alg, self.venv
        venv.stats.clear()
        start = time.perf_counter()
        obs = venv.get_observations()
        with torch.inference_mode():
            for _ in range(self.steps_per_env):
                if self.anchor is not None:
                    self.anchor.observe(obs["actor"].cpu().numpy())
                actions = alg.act(obs)
                obs, rewards, dones, extras = venv.step(actions)
                alg.process_env_step(obs, rewards, dones, extras)
            alg.compute_returns(obs)
        return start, time.perf_counter()

    def _learn(self, start: float, collected: float) -> dict[str, float]:
        """The update from the collected rollout, and the counters; the iteration's figures."""
        alg, venv = self.alg, self.venv
        losses = alg.update()
        anchored = self.anchor.learn() if self.anchor is not None else {}
        learned = time.perf_counter()
        self.iteration += 1
        self.env_steps += self.batch
        self.elapsed += learned - start
        figures = venv.stats.summary(self.env.sim.policy_dt)
        figures.update({f"loss/{k}": float(v) for k, v in losses.items()})
        figures.update(anchored)
        figures.update({
            "policy/learning_rate": float(alg.learning_rate),
            "policy/action_std": float(alg.get_policy().output_std.detach().mean()),
            "curriculum/progress": self.env.progress,
            "curriculum/noise_factor": self.env.noise_factor,
            "curriculum/penalty_factor": self.env.penalty_factor,
            "curriculum/randomization_width": self.env.randomization_width,
            "episode/start_concentration": self.env.starts.concentration(),
            "perf/env_steps_per_s": self.local_batch / (collected - start),
            "perf/learner_samples_per_s": self.local_batch * self.ppo.num_learning_epochs / (learned - collected),
            "perf/iteration_s": learned - start,
        })
        return self.group.combine(figures)

    def train(self, schedule: Schedule, progress: bool = True, writer=None,
              stop_after: int | None = None) -> dict[str, float]:
        """Train until `schedule.total_steps` environment steps (or, with `stop_after`, until that
        many iterations are done; the schedule's total still sets the curriculum progress);
        checkpoint periodically and at the end, and when interrupted by Ctrl-C or SIGTERM (the
        rollout in flight is dropped; an interrupt during an update takes effect when it ends, so
        the checkpoint holds every whole iteration)."""
        total_iterations = self.iterations_for(schedule.total_steps)
        last = total_iterations if stop_after is None else min(stop_after, total_iterations)
        bar = _bar(progress, total_iterations * self.batch, self.env_steps)
        last_save, figures = time.monotonic(), {}
        try:
            while self.iteration < last:
                if self.pace is None:
                    done = self.env_steps / (total_iterations * self.batch)
                    self.env.set_progress(self.curriculum_start + (1.0 - self.curriculum_start) * done)
                timing = self._collect()  # an interrupt here drops the rollout in flight
                # ... but not the update: it ends with its counters, curriculum and log line first
                with processes.interrupts_held():
                    figures = self._learn(*timing)
                    if self.pace is not None:  # the next iteration's world, from this one's failures
                        self.env.set_progress(self.pace.advance(self.env.progress, figures,
                                                                self.batch * self.env.sim.policy_dt))
                    self._log(figures, writer)
                    if bar is not None:
                        bar.update(self.batch)
                        bar.set_postfix_str(_postfix(figures), refresh=False)
                due = self.iteration % schedule.checkpoint_every == 0 or (
                    time.monotonic() - last_save > 60 * schedule.checkpoint_minutes)
                judged = self.judge is not None and (self.judge.due(self.iteration) or self.iteration == last)
                if self.writes and (due or judged or self.iteration == last):
                    saved = self.save()
                    last_save = time.monotonic()
                    if judged:
                        self._log(judge_actor(self.judge, self.alg.actor, saved, "ppo", self.iteration,
                                              self.env_steps, self.elapsed), writer, progress_file=False)
                if self.group.stop_requested():  # a process of the group was stopped: all end here
                    raise KeyboardInterrupt
        except KeyboardInterrupt:
            if self.writes and self.iteration > 0:
                self.save()  # the networks of the last whole iteration (the rollout in flight is dropped)
            raise
        finally:
            if bar is not None:
                bar.close()
        return figures

    @property
    def writes(self) -> bool:
        """Whether this trainer writes the run (checkpoints, progress): rank 0 of a group does."""
        return self.run is not None and self.group.is_main

    def _log(self, figures: dict[str, float], writer, progress_file: bool = True) -> None:
        if not self.group.is_main:
            return
        if not progress_file:  # figures about the iteration just logged (TensorBoard only)
            log_iteration(None, writer, self.iteration, self.env_steps, self.elapsed, figures)
            return
        log_iteration(self.run, writer, self.iteration, self.env_steps, self.elapsed,
                      {**figures, "perf/env_steps_total": self.env_steps})


def log_iteration(run: Path | None, writer, iteration: int, env_steps: int, elapsed: float,
                  figures: dict[str, float]) -> None:
    """One iteration's figures: TensorBoard scalars at step `iteration` (if a writer is given) and a
    line of RUN/progress.jsonl (if a run directory is given)."""
    if writer is not None:
        for key, value in figures.items():
            writer.add_scalar(key, value, iteration)
    if run is not None:
        record = {"iteration": iteration, "env_steps": env_steps, "elapsed": elapsed, **figures}
        with open(Path(run) / PROGRESS_FILE, "a") as f:
            f.write(dumps(record) + "\n")


def _bar(enabled: bool, total: int, done: int):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, initial=done, unit="step", unit_scale=True, desc="training", dynamic_ncols=True)


def _postfix(f: dict[str, float]) -> str:
    parts = [f"reward/step {f['reward/step']:.3f}"]
    if "episode/length_s" in f:
        parts.append(f"episode {f['episode/length_s']:.2f} s")
    parts.append(f"env {f['perf/env_steps_per_s']:.0f}/s")
    return ", ".join(parts)
