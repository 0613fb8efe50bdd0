"""A trained actor as a deterministic policy: observation normalizer + MLP, numpy in, numpy out.

`load_policy(run)` rebuilds the actor of a run's newest (or a given) checkpoint from the run's own
configuration, so evaluation, export (ONNX, `Policy.module`) and distillation read one place.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch
from rsl_rl.models import MLPModel
from rsl_rl.utils import resolve_class
from tensordict import TensorDict

from opt2skill.data.record import FRAME_DT
from opt2skill.errors import DataError
from opt2skill.rl import checkpoint
from opt2skill.rl.config import PPOConfig
from opt2skill.rl.residual import hidden_dims
from opt2skill.rl.run import RunSpec, read_spec


def build_actor(ppo: PPOConfig, actor_dim: int, critic_dim: int, num_actions: int) -> MLPModel:
    """An untrained actor with the architecture of `ppo` (what the trainer builds)."""
    cfg = ppo.rsl_rl(FRAME_DT)
    cls, kwargs = resolve_class(cfg["actor"])
    obs = TensorDict({"actor": torch.zeros(1, actor_dim), "critic": torch.zeros(1, critic_dim)}, batch_size=[1])
    return cls(obs, cfg["obs_groups"], "actor", num_actions, **kwargs)


class Policy:
    """Deterministic actions (the Gaussian's mean) of an actor, observation normalization included."""

    def __init__(self, actor: MLPModel, iteration: int = 0, env_steps: int = 0):
        self.actor = actor.eval()
        # A copy of the normalizer and MLP on a flat observation, on the CPU whatever device trains the actor.
        self.module = actor.as_onnx(verbose=False).eval().cpu()
        self.iteration, self.env_steps = iteration, env_steps
        self.obs_dim = actor.obs_dim

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return self.module(torch.as_tensor(obs, dtype=torch.float32)).numpy()


def load_policy(run: Path, path: Path | None = None) -> tuple[Policy, RunSpec]:
    """The policy of `run`'s newest checkpoint (or of `path`) and the run's spec."""
    spec = read_spec(run)
    path = path or checkpoint.latest(run)
    if path is None:
        raise DataError(f"{run} has no checkpoint yet")
    data = checkpoint.load(Path(path))
    obs = spec.tracking.observations
    checkpoint.check_identity(Path(path), data, checkpoint.identity(
        spec.robot, spec.robot_hash, spec.tracking.task, spec.tracking.ablation, obs.history, obs.stride))
    dims = data["dims"]
    # A PPO checkpoint holds rsl_rl's state; a distillation stage's holds the actor alone. Its widths are
    # read from the weights: a residual run's distillation stage has narrower layers than its PPO stage.
    state = data["alg"]["actor_state_dict"] if "alg" in data else data["actor_state_dict"]
    ppo = dataclasses.replace(spec.ppo, hidden_dims=hidden_dims(state))
    actor = build_actor(ppo, dims["actor"], dims["critic"], dims["actions"])
    actor.load_state_dict(state)
    return Policy(actor, data["iteration"], data["env_steps"]), spec
