"""PPO settings for a 200 Hz control rate, and their translation into rsl_rl's configuration.

Time constants are given in seconds and converted with the policy step dt (docs/training.md):
gamma = exp(-dt / discount_horizon), gamma * lambda = exp(-dt / gae_horizon), rollout steps =
round(rollout_seconds / dt). At 200 Hz, the usual 50 Hz values (gamma 0.99, lambda 0.95, 24 steps)
would shrink every horizon four times.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from opt2skill.errors import ConfigError


def native_bf16(cpuinfo: str | None = None) -> bool | None:
    """Whether this CPU computes bf16 natively (`avx512_bf16` or `amx_bf16` among its flags), from
    `cpuinfo` (default: /proc/cpuinfo); None where that cannot be read (not Linux)."""
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo") as f:
                cpuinfo = f.read()
        except OSError:
            return None
    flags = {flag for line in cpuinfo.splitlines() if line.startswith("flags") for flag in line.split(":", 1)[-1].split()}
    return bool(flags & {"avx512_bf16", "amx_bf16"})


@dataclass(frozen=True)
class PPOConfig:
    hidden_dims: tuple[int, ...] = (512, 512, 256, 256)  # actor and critic, Section III-B
    activation: str = "elu"
    init_std: float = 0.2  # initial action noise, in action units (x ActionConfig.scale rad): 0.1 rad
    actor_output_gain: float = 0.01  # the untrained actor's last layer is scaled by this: mean action ~0
    discount_horizon: float = 1.0  # s
    gae_horizon: float = 0.33  # s
    rollout_seconds: float = 0.24  # s of experience per world per iteration
    num_learning_epochs: int = 5
    num_mini_batches: int = 4
    clip_param: float = 0.2
    value_loss_coef: float = 1.0
    entropy_coef: float = 0.005
    learning_rate: float = 5e-5  # initial (schedule "adaptive": adapted to keep the KL near desired_kl)
    schedule: str = "adaptive"  # or "fixed"
    desired_kl: float = 0.01
    max_grad_norm: float = 1.0
    reward_scale: float = 0.0  # factor on rewards fed to PPO; 0: the policy step dt (returns in seconds)
    # bf16 autocast in PPO's update (rsl_rl's use_mixed_precision; weights, optimizer and rollouts stay
    # float32): 2.7 times the learner's samples/s on a CPU with AVX512-BF16, slower where bf16 is
    # emulated (docs/training.md). Off by default: the paper's runs and ours are float32.
    mixed_precision: bool = False

    def check(self) -> None:
        def require(ok: bool, message: str) -> None:
            if not ok:
                raise ConfigError(message)

        require(len(self.hidden_dims) > 0 and all(d > 0 for d in self.hidden_dims), "hidden_dims must be positive sizes")
        require(self.init_std > 0, f"init_std must be > 0, got {self.init_std}")
        require(0 < self.actor_output_gain <= 1, f"actor_output_gain must be in (0, 1], got {self.actor_output_gain}")
        require(0 < self.gae_horizon <= self.discount_horizon,
                f"horizons must satisfy 0 < gae_horizon <= discount_horizon, got {self.gae_horizon}, {self.discount_horizon}")
        require(self.rollout_seconds > 0, f"rollout_seconds must be > 0, got {self.rollout_seconds}")
        require(self.num_learning_epochs >= 1 and self.num_mini_batches >= 1, "epochs and mini-batches must be >= 1")
        require(self.learning_rate > 0 and self.desired_kl > 0, "learning_rate and desired_kl must be > 0")
        require(self.schedule in ("adaptive", "fixed"), f"schedule must be 'adaptive' or 'fixed', got '{self.schedule}'")
        require(self.reward_scale >= 0, f"reward_scale must be >= 0, got {self.reward_scale}")

    def gamma(self, dt: float) -> float:
        return math.exp(-dt / self.discount_horizon)

    def lam(self, dt: float) -> float:
        return math.exp(-dt / self.gae_horizon) / self.gamma(dt)

    def steps_per_env(self, dt: float) -> int:
        return max(1, round(self.rollout_seconds / dt))

    def rsl_rl(self, dt: float) -> dict:
        """The configuration dict `rsl_rl.algorithms.PPO.construct_algorithm` reads."""
        self.check()
        model = {"class_name": "rsl_rl.models:MLPModel", "hidden_dims": list(self.hidden_dims),
                 "activation": self.activation, "obs_normalization": True}
        return {
            "algorithm": {
                "class_name": "rsl_rl.algorithms:PPO",
                "num_learning_epochs": self.num_learning_epochs,
                "num_mini_batches": self.num_mini_batches,
                "clip_param": self.clip_param,
                "gamma": self.gamma(dt),
                "lam": self.lam(dt),
                "value_loss_coef": self.value_loss_coef,
                "entropy_coef": self.entropy_coef,
                "learning_rate": self.learning_rate,
                "max_grad_norm": self.max_grad_norm,
                "use_clipped_value_loss": True,
                "schedule": self.schedule,
                "desired_kl": self.desired_kl,
                "use_mixed_precision": self.mixed_precision,
            },
            "actor": {**model, "distribution_cfg": {"class_name": "rsl_rl.modules.distribution:GaussianDistribution",
                                                    "init_std": self.init_std, "std_type": "scalar"}},
            "critic": dict(model),
            "obs_groups": {"actor": ["actor"], "critic": ["critic"]},
            "num_steps_per_env": self.steps_per_env(dt),
            "multi_gpu": None,
        }
