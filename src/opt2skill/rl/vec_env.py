"""The tracking environment as an rsl_rl `VecEnv`: torch tensors, observation groups in a TensorDict.

Groups: "actor" and "critic" (Section III-B's asymmetric observations). Rewards handed to PPO are
the Table I rewards times `reward_scale` (the policy step, by default: returns become time
integrals, docs/training.md); the unscaled rewards and every term are kept for logging in `stats`.
"""

from __future__ import annotations

import numpy as np
import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from opt2skill.envs import CAUSES, StepResult, TrackingEnv


class EpisodeStats:
    """Running sums of what the environment reports, read and cleared once per iteration."""

    def __init__(self, terms: tuple[str, ...]):
        self.terms = terms
        self.clear()

    def clear(self) -> None:
        self.steps = 0
        self.reward_sum = 0.0
        self.term_sums = dict.fromkeys(self.terms, 0.0)
        self.episode_lengths: list[np.ndarray] = []
        self.episode_rewards: list[np.ndarray] = []
        self.causes = np.zeros(len(CAUSES), dtype=np.int64)
        self.unstable = 0
        self.pushed = 0

    def add(self, result: StepResult) -> None:
        n = len(result.reward)
        self.steps += n
        self.reward_sum += float(result.reward.sum())
        for name, value in result.terms.items():
            self.term_sums[name] += float(value.sum())
        self.unstable += result.unstable
        self.pushed += result.pushed
        if result.episodes is not None:
            self.episode_lengths.append(result.episodes.length)
            self.episode_rewards.append(result.episodes.reward)
            self.causes += np.bincount(result.episodes.cause, minlength=len(CAUSES))

    def summary(self, policy_dt: float) -> dict[str, float]:
        """Per-step means of the reward and each term, episode figures, termination counts."""
        out = {"reward/step": self.reward_sum / max(self.steps, 1)}
        out.update({f"reward_terms/{name}": s / max(self.steps, 1) for name, s in self.term_sums.items()})
        if self.episode_lengths:
            lengths = np.concatenate(self.episode_lengths)
            out["episode/length_steps"] = float(lengths.mean())
            out["episode/length_s"] = float(lengths.mean() * policy_dt)
            out["episode/reward"] = float(np.concatenate(self.episode_rewards).mean())
            out["episode/count"] = float(len(lengths))
        for name, count in zip(CAUSES, self.causes):
            out[f"terminations/{name}"] = float(count)
        out["terminations/unstable_worlds"] = float(self.unstable)
        out["randomization/pushes"] = float(self.pushed)
        return out


class TrackingVecEnv(VecEnv):
    """`device`: where the learner is (rsl_rl's `VecEnv.device`); the environment's numpy arrays are
    copied there each step, and the actions back."""

    def __init__(self, env: TrackingEnv, reward_scale: float | None = None, device: str = "cpu"):
        self.env = env
        self.num_envs = env.num_envs
        self.num_actions = env.nu
        self.max_episode_length = int(env.bank.length.max())
        self.device = torch.device(device)
        self.episode_length_buf = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self.cfg = {}
        self.reward_scale = env.sim.policy_dt if reward_scale is None else reward_scale
        self.stats = EpisodeStats(tuple(env.config.rewards.terms()))
        self._obs = self._wrap(*env.observations())

    def _tensor(self, array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(array).to(self.device)

    def _wrap(self, actor: np.ndarray, critic: np.ndarray) -> TensorDict:
        return TensorDict({"actor": self._tensor(actor), "critic": self._tensor(critic)},
                          batch_size=[self.num_envs], device=self.device)

    def refresh(self) -> None:
        """Read the observations again (after the environment was reset outside `step`)."""
        self._obs = self._wrap(*self.env.observations())

    def get_observations(self) -> TensorDict:
        return self._obs

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        result = self.env.step(actions.detach().cpu().numpy())
        self.stats.add(result)
        self._obs = self._wrap(result.actor, result.critic)
        self.episode_length_buf = self._tensor(self.env.steps)
        rewards = self._tensor((result.reward * self.reward_scale).astype(np.float32))
        dones = self._tensor(result.terminated | result.truncated)
        extras = {"time_outs": self._tensor(result.truncated)}
        return self._obs, rewards, dones, extras
