"""The distillation's loss kept during PPO: an anchor to the optimizer's feedback expert.

PPO's first updates move a distilled actor off the expert's behaviour (docs/distill.md measures
1 % of weight change undoing it). The anchor labels the states PPO visits with the expert's action
wherever the expert is still valid (DAgger labels on the PPO stage's own states, under its full
randomization), and after each PPO update takes `anchor_updates` Adam steps of the same
behaviour-cloning loss on the newest labels. PPO's gradient can then move the actor only where the
expert does not pull it back.

The trainer calls `observe(actor_obs)` before each action (the environment is then in the state the
observation describes) and `learn()` after each PPO update; `learn` does nothing while the actor is
frozen (the critic warm-up). The optimizer and random generator are checkpointed with the PPO
stage; the label buffer is refilled after a resume, as in the distillation stage.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from rsl_rl.models import MLPModel

from opt2skill.expert.acting import EnvExpert
from opt2skill.rl.distill import LabelBuffer, clone_steps
from opt2skill.rl.distill_config import DistillConfig
from opt2skill.rl.processes import ONE, Group


class ExpertAnchor:
    def __init__(self, expert: EnvExpert, actor: MLPModel, config: DistillConfig, seed: int = 0, group: Group = ONE):
        env = expert.env
        self.expert, self.actor, self.config, self.group = expert, actor, config, group
        self.buffer = LabelBuffer(config.buffer_samples, env.actor_dim, env.nu)
        self.optimizer = torch.optim.Adam(actor.parameters(), lr=config.anchor_learning_rate)
        self.generator = torch.Generator().manual_seed(group.seed(seed))
        self._seen = self._labelled = 0

    def observe(self, actor_obs: np.ndarray) -> None:
        """Label the worlds' current states (whose observations are `actor_obs`) where the expert is valid."""
        action, valid = self.expert.act()
        self.buffer.add(actor_obs[valid], action[valid])
        self._seen += len(valid)
        self._labelled += int(valid.sum())

    def learn(self) -> dict[str, float]:
        figures = {"anchor/labelled_fraction": self._labelled / max(self._seen, 1)}
        self._seen = self._labelled = 0
        trainable = any(p.requires_grad for p in self.actor.parameters())
        # Every process of a group must take the same steps (their gradients are averaged).
        if self.group.everyone(trainable and self.buffer.size >= self.config.batch_size // self.group.size):
            training = self.actor.training
            self.actor.train()
            figures["anchor/loss"] = clone_steps(self.actor, self.optimizer, self.buffer, self.config.batch_size,
                                                 self.config.anchor_updates, self.generator, self.group)
            self.actor.train(training)
        return figures

    def state(self) -> dict[str, Any]:
        return {"optimizer_state_dict": self.optimizer.state_dict(), "torch_rng": self.generator.get_state()}

    def restore(self, data: dict[str, Any]) -> None:
        self.optimizer.load_state_dict(data["optimizer_state_dict"])
        self.generator.set_state(data["torch_rng"])
