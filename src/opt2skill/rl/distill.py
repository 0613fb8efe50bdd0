"""Distillation of the optimizer's feedback expert into the PPO actor (DAgger with DART noise).

The actor is the network PPO trains (`rl.policy.build_actor`), fed the actor observations of the
tracking environment (the noisy proprioception and partial reference; never the privileged state).
Each iteration:

1. **Collect** `steps_per_env` steps of every world. The executed action is
   `share * expert + (1 - share) * actor + action_noise * N(0, 1)`; the expert's share falls from 1
   to 0 over the first part of the stage (DAgger's mixing, DART's injected noise). Every visited
   state where the expert is still valid (`ExpertConfig` limits) is stored with the expert's action
   as its label; a world that leaves the expert's valid region is reset (nothing to learn there).
   The actor's observations carry Table II's noise times `DistillConfig.noise` (default 0); the
   expert reads the true state.
2. **Learn**: `updates_per_iteration` Adam steps of mean-squared action error on minibatches of the
   aggregated buffer (the newest `buffer_samples` labels). The observation normalizer follows the
   collected observations.

The worlds are stepped together and the expert labels them together (`EnvExpert.act`): no loop over
worlds. Checkpoints (`rl.checkpoint`, under RUN/distill) hold the actor, the optimizer, the counters
and the random generators; the aggregated buffer is not saved (a resumed stage refills it).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from rsl_rl.models import MLPModel
from tensordict import TensorDict

from opt2skill.envs import TrackingEnv
from opt2skill.expert.acting import EnvExpert
from opt2skill.rl import checkpoint, processes
from opt2skill.rl.best import judge_actor
from opt2skill.rl.distill_config import DistillConfig
from opt2skill.rl.processes import ONE, Group
from opt2skill.rl.run import trim_progress
from opt2skill.rl.trainer import log_iteration
from opt2skill.rl.vec_env import EpisodeStats


class LabelBuffer:
    """The newest `capacity` (observation, expert action) pairs, a ring buffer of float32 tensors."""

    def __init__(self, capacity: int, obs_dim: int, nu: int):
        self.obs = torch.zeros(capacity, obs_dim)
        self.label = torch.zeros(capacity, nu)
        self.capacity, self.size, self._next = capacity, 0, 0

    def add(self, obs: np.ndarray, label: np.ndarray) -> None:
        k = len(obs)
        if k == 0:
            return
        if k > self.capacity:
            obs, label, k = obs[-self.capacity:], label[-self.capacity:], self.capacity
        index = (self._next + np.arange(k)) % self.capacity
        self.obs[index] = torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32))
        self.label[index] = torch.from_numpy(np.ascontiguousarray(label, dtype=np.float32))
        self._next = (self._next + k) % self.capacity
        self.size = min(self.size + k, self.capacity)

    def sample(self, batch: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        index = torch.randint(0, self.size, (batch,), generator=generator)
        return self.obs[index], self.label[index]


def clone_steps(actor: MLPModel, optimizer: torch.optim.Optimizer, buffer: LabelBuffer, batch_size: int,
                updates: int, generator: torch.Generator, group: Group = ONE) -> float:
    """`updates` optimizer steps of mean-squared action error on minibatches of `buffer`; the mean loss.
    In a group of processes each samples `batch_size / size` of its own buffer and the gradients are
    averaged: the gradient of one `batch_size` minibatch, as in one process, for the same work."""
    batch_size = max(1, batch_size // group.size)
    device = next(actor.parameters()).device  # the buffer is on the CPU; a PPO actor may learn on a GPU
    losses = []
    for _ in range(updates):
        obs, label = (x.to(device) for x in buffer.sample(batch_size, generator))
        prediction = actor(TensorDict({"actor": obs}, batch_size=[len(obs)]))
        loss = torch.mean((prediction - label) ** 2)
        optimizer.zero_grad()
        loss.backward()
        group.average_gradients(actor.parameters())
        torch.nn.utils.clip_grad_norm_(actor.parameters(), 1.0)
        optimizer.step()
        losses.append(loss.item())
    return float(np.mean(losses))


class Distiller:
    """DAgger + DART behaviour cloning of `expert` into `actor` on `env`."""

    def __init__(self, env: TrackingEnv, expert: EnvExpert, actor: MLPModel, config: DistillConfig,
                 run: Path | None = None, seed: int = 0, group: Group = ONE):
        """`group`: one of several processes distilling together (`rl.processes`), as `Trainer`'s:
        rank 0's actor to start, gradients and normalizer statistics averaged, rank 0 writes `run`."""
        config.check()
        self.env, self.expert, self.actor, self.config = env, expert, actor, config
        self.run = Path(run) if run is not None else None
        self.group, self.seed = group, seed
        group.share_module(actor)
        self.steps_per_env = config.steps_per_env(env.sim.policy_dt)
        self.local_batch = env.num_envs * self.steps_per_env
        self.batch = group.size * self.local_batch  # environment steps per iteration, all processes
        self.optimizer = torch.optim.Adam(actor.parameters(), lr=config.learning_rate)
        self.buffer = LabelBuffer(config.buffer_samples, env.actor_dim, env.nu)
        self.generator = torch.Generator().manual_seed(group.seed(seed))
        self.rng = np.random.default_rng(group.seed(seed))
        self.stats = EpisodeStats(tuple(env.config.rewards.terms()))
        self.iteration, self.env_steps, self.elapsed = 0, 0, 0.0
        self.total_iterations = 1
        self.judge = None  # optional `rl.best.HeldOutJudge`, as `Trainer.judge`
        self._set_noise()
        self._obs, _ = env.observations()

    # ------------------------------------------------------------ one iteration

    def _set_noise(self) -> None:
        self.env.set_progress(1.0)  # penalties at full weight in the logged rewards
        self.env.noise_factor = self.config.noise

    @property
    def progress(self) -> float:
        return min(self.iteration / max(self.total_iterations, 1), 1.0)

    def collect(self) -> dict[str, float]:
        """One rollout of every world; labels into the buffer. The rollout's figures."""
        env, cfg = self.env, self.config
        share = cfg.expert_share(self.progress)
        labelled = lost = 0
        self.stats.clear()
        self.actor.train()
        seen = []
        for _ in range(self.steps_per_env):
            expert_action, valid = self.expert.act()
            stray = np.flatnonzero(~valid)
            if len(stray):  # left the expert's region: nothing to learn there, start these worlds afresh
                lost += len(stray)
                env.fail_worlds(stray)  # a failure of the actor's (or the expert's): adaptive starts weigh it
                self._obs = env.observations()[0]
                expert_action, valid = self.expert.act()
            obs = self._obs
            seen.append(obs)
            self.buffer.add(obs[valid], expert_action[valid])
            labelled += int(valid.sum())
            action = expert_action
            if share < 1.0:
                with torch.inference_mode():
                    own = self.actor(TensorDict({"actor": torch.from_numpy(obs)}, batch_size=[len(obs)])).numpy()
                action = share * expert_action + (1.0 - share) * own
            if cfg.action_noise > 0:
                action = action + cfg.action_noise * self.rng.standard_normal(action.shape)
            result = env.step(action)
            self.stats.add(result)
            self._obs = result.actor
        seen = torch.from_numpy(np.concatenate(seen))
        self.actor.update_normalization(TensorDict({"actor": seen}, batch_size=[len(seen)]))
        figures = self.stats.summary(env.sim.policy_dt)
        figures.update({"distill/expert_share": share, "distill/labelled_fraction": labelled / self.local_batch,
                        "distill/expert_lost_worlds": float(lost), "distill/buffer_samples": float(self.buffer.size),
                        "episode/start_concentration": env.starts.concentration()})
        return figures

    def learn(self) -> dict[str, float]:
        """`updates_per_iteration` Adam steps of behaviour cloning on the buffer."""
        cfg = self.config
        lr = cfg.learning_rate_at(self.progress)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        self.actor.train()
        loss = clone_steps(self.actor, self.optimizer, self.buffer, cfg.batch_size, cfg.updates_per_iteration,
                           self.generator, self.group)
        return {"distill/loss": loss, "distill/learning_rate": lr}

    def train_iteration(self) -> dict[str, float]:
        start = time.perf_counter()
        return self._learn(self.collect(), start, time.perf_counter())

    def _learn(self, figures: dict[str, float], start: float, collected: float) -> dict[str, float]:
        """The updates from the collected rollout, and the counters; the iteration's figures."""
        figures.update(self.learn())
        learned = time.perf_counter()
        self.iteration += 1
        self.env_steps += self.batch
        self.elapsed += learned - start
        figures.update({"perf/env_steps_per_s": self.local_batch / (collected - start),
                        "perf/learner_samples_per_s": self.config.updates_per_iteration * self.config.batch_size
                        // self.group.size
                        / (learned - collected), "perf/iteration_s": learned - start})
        return self.group.combine(figures)

    # ------------------------------------------------------------ the stage

    def train(self, total_iterations: int, progress: bool = True, writer=None,
              checkpoint_every: int = 50, checkpoint_minutes: float = 5.0) -> dict[str, float]:
        """Run until `total_iterations`; checkpoint periodically, at the end and on Ctrl-C/SIGTERM (an
        interrupt during the updates takes effect when they end: the checkpoint holds whole iterations)."""
        self.total_iterations = total_iterations
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=total_iterations * self.batch, initial=self.iteration * self.batch, unit="step",
                       unit_scale=True, desc="distilling", dynamic_ncols=True)
        last_save, figures = time.monotonic(), {}
        try:
            while self.iteration < total_iterations:
                start = time.perf_counter()
                collected = self.collect()  # an interrupt here drops the rollout in flight
                with processes.interrupts_held():  # ... but not the updates: they end, counted and logged, first
                    figures = self._learn(collected, start, time.perf_counter())
                    self._log(figures, writer)
                    if bar is not None:
                        bar.update(self.batch)
                        bar.set_postfix_str(f"loss {figures['distill/loss']:.4f}, "
                                            f"expert {figures['distill/expert_share']:.2f}", refresh=False)
                due = self.iteration % checkpoint_every == 0 or time.monotonic() - last_save > 60 * checkpoint_minutes
                judged = self.judge is not None and (self.judge.due(self.iteration) or self.iteration == total_iterations)
                if self.writes and (due or judged or self.iteration == total_iterations):
                    saved = self.save()
                    last_save = time.monotonic()
                    if judged:
                        self._log(judge_actor(self.judge, self.actor, saved, "distill", self.iteration,
                                              self.env_steps, self.elapsed), writer, progress_file=False)
                if self.group.stop_requested():  # a process of the group was stopped: all end here
                    raise KeyboardInterrupt
        except KeyboardInterrupt:
            if self.writes and self.iteration > 0:
                self.save()  # the last whole iteration; the rollout in flight is dropped
            raise
        finally:
            if bar is not None:
                bar.close()
        return figures

    @property
    def writes(self) -> bool:
        """Whether this distiller writes the stage's checkpoints and progress: rank 0 of a group does."""
        return self.run is not None and self.group.is_main

    def _log(self, figures: dict[str, float], writer, progress_file: bool = True) -> None:
        if not self.group.is_main:
            return
        log_iteration(self.run if progress_file else None, writer, self.iteration, self.env_steps, self.elapsed,
                      figures)

    # ------------------------------------------------------------ checkpoints

    def state(self) -> dict[str, Any]:
        return {
            "actor_state_dict": self.actor.state_dict(),
            "optimizer_state_dict": self.optimizer.state_dict(),
            "env_steps": self.env_steps,
            "elapsed": self.elapsed,
            "total_iterations": self.total_iterations,
            "torch_rng": self.generator.get_state(),
            "rng": self.rng.bit_generator.state,
            "env_rng": self.env.rng.bit_generator.state,
            "starts": self.env.starts.state(),
            "dims": {"actor": self.env.actor_dim, "critic": self.env.critic_dim, "actions": self.env.nu},
            "identity": self.identity(),
        }

    def identity(self) -> dict[str, Any]:
        env, obs = self.env, self.env.config.observations
        return checkpoint.identity(env.robot.name, env.robot.hash, env.config.task, env.config.ablation, obs.history,
                                   obs.stride)

    def save(self) -> Path:
        return checkpoint.save(self.run, self.iteration, self.state())

    def restore(self, data: dict[str, Any], path: Path | str = "checkpoint") -> None:
        checkpoint.check_identity(Path(path), data, self.identity())
        self.actor.load_state_dict(data["actor_state_dict"])
        self.optimizer.load_state_dict(data["optimizer_state_dict"])
        self.iteration, self.env_steps, self.elapsed = data["iteration"], data["env_steps"], data["elapsed"]
        self.total_iterations = data["total_iterations"]
        self.generator.set_state(data["torch_rng"])
        self.rng.bit_generator.state = data["rng"]
        self.env.rng.bit_generator.state = data["env_rng"]
        if "starts" in data:
            self.env.starts.restore(data["starts"])
        if not self.group.is_main:  # the checkpoint holds rank 0's streams: the others draw fresh ones of their own
            seed = self.group.seed(self.seed) + self.iteration
            self.generator.manual_seed(seed)
            self.rng = np.random.default_rng(seed)
            self.env.rng.bit_generator.state = np.random.default_rng(seed + 1).bit_generator.state
        self.env.reset()
        self._set_noise()
        self._obs, _ = self.env.observations()

    def resume_latest(self) -> bool:
        path = checkpoint.latest(self.run) if self.run is not None else None
        if path is None:
            return False
        self.restore(checkpoint.load(path), path)
        if self.group.is_main:
            trim_progress(self.run, self.iteration)
        return True
