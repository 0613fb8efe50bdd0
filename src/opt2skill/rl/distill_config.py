"""Settings of the two-stage pipeline: distil the optimizer's feedback expert into the actor, then PPO.

One frozen dataclass with defaults (docs/distill.md gives the reasoning and the measurements):

- the expert (`ExpertConfig`: how its torques become held PD targets, how far it is trusted);
- the conditions it is distilled under: the Table II randomizations it tolerates, narrowed from the
  task's config by `distillation_tracking_config` (flat ground, short delays, friction near the
  plan's, robot-side ranges halved), and the actor's observation noise, a factor on Table II (the
  labels never see it; docs/distill.md measures why it is off);
- DAgger with DART noise: the executed action blends the expert's and the actor's, the expert's share
  falling from 1 to 0 over `expert_share_until` of the stage, plus Gaussian noise on what is executed;
  every visited state where the expert is still valid is labelled with the expert's action;
- behaviour cloning: mean-squared action error on an aggregated buffer of labelled samples;
- the PPO stage: small initial action noise, a critic warm-up with the actor frozen, the noise
  curriculum starting where the distillation left it (`finetune_tracking_config`), and the
  behaviour-cloning loss kept as an anchor between PPO updates (`rl.anchor`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from opt2skill.envs.config import TrackingConfig
from opt2skill.errors import ConfigError
from opt2skill.expert.acting import ExpertConfig
from opt2skill.rl.config import PPOConfig

ROBOT_SIDE = ("motor_strength", "kp_factor", "kd_factor", "mass_scale", "gravity_scale")


@dataclass(frozen=True)
class DistillConfig:
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    # Conditions of the distillation stage (the expert's tolerated part of Table II).
    delay: tuple[float, float] = (0.0, 0.005)  # s
    friction_scale: tuple[float, float] = (0.7, 1.0)
    robot_range: float = 0.5  # fraction of Table II's robot-side ranges kept, around 1
    rough_fraction: float = 0.0  # the expert falls on the +-2 cm rough terrain
    push_speed: float = 0.0  # m/s, largest push while distilling (the expert is a local law)
    noise: float = 0.0  # factor on the actor's observation noise (Table II) while distilling (docs/distill.md)
    # DAgger and DART.
    rollout_seconds: float = 0.12  # s of experience per world per iteration
    expert_share_until: float = 0.3  # fraction of the stage over which the expert's share falls 1 -> 0
    action_noise: float = 0.1  # std of the Gaussian added to executed actions, action units
    # Behaviour cloning.
    buffer_samples: int = 200_000  # labelled samples kept (the newest)
    batch_size: int = 2048
    updates_per_iteration: int = 8  # about 5-10 gradient uses per collected sample at 64-128 worlds
    learning_rate: float = 1e-3  # Adam, decayed linearly to `final_learning_rate` over the stage
    final_learning_rate: float = 1e-4
    # PPO fine-tuning.
    finetune_std: float = 0.1  # initial action std of PPO, action units (plain PPO starts at 0.2)
    # Initial PPO learning rate (then adapted to the KL as in plain PPO). The KL of an update grows as
    # (mean change / std)^2: at half plain PPO's std, half its rate moves the policy as far.
    finetune_learning_rate: float = 2.5e-5
    critic_warmup_iterations: int = 30  # PPO iterations with the actor frozen
    # The distillation's loss kept during PPO (`rl.anchor`): Adam steps on expert labels of the PPO
    # stage's states after each PPO update (0: none).
    anchor_updates: int = 8
    anchor_learning_rate: float = 1e-4
    # Factor on Table II's observation noise that the PPO stage's curriculum rises to: 1 is the paper;
    # less is a diagnostic of what the noise costs (docs/distill.md), not a deployable policy.
    finetune_noise: float = 1.0
    # Width of Table II's randomization ranges (around the nominal world) that the PPO stage's
    # curriculum starts from, rising to 1 with the noise: 1 randomizes in full from the first
    # iteration (the paper's way), which wrecks the distilled actor fastest (docs/distill.md). 0.25 is
    # about the distillation's conditions (its delays of 5 ms are a quarter of Table II's 20 ms).
    finetune_randomization: float = 0.25
    # What PPO trains after distillation: "full" (the distilled actor's weights, the paper's way) or
    # "residual" (`rl.residual`: the distilled actor frozen, extra units of `residual_dims` per hidden
    # layer learn a correction added to its action).
    finetune: str = "full"
    residual_dims: tuple[int, ...] = (128, 128, 64, 64)
    # How the PPO stage's curriculum (noise, penalties, randomization width) advances: "clock" (with
    # the environment steps, over --steps, the paper's) or "adaptive" (`rl.pace.AdaptivePace`: a step
    # of `adaptive_step` after each iteration whose worlds fell less than `adaptive_fall_rate` times
    # per second of experience, so the world widens only as fast as the policy copes).
    pace: str = "clock"
    adaptive_step: float = 0.005
    # Falls per world-second: about what the distilled actor does at the stage's starting conditions
    # (0.06-0.1 measured on 98 walks, 2026-12-01), so the world widens as PPO makes falls rarer.
    adaptive_fall_rate: float = 0.1

    def check(self) -> None:
        def require(ok: bool, message: str) -> None:
            if not ok:
                raise ConfigError(message)

        self.expert.check()
        for name in ("delay", "friction_scale"):
            lo, hi = getattr(self, name)
            require(0 <= lo <= hi, f"distill {name} must be a range 0 <= low <= high, got ({lo}, {hi})")
        require(self.delay[1] <= 0.02, f"distill delay must be at most 0.02 s, got {self.delay[1]}")
        require(0 <= self.robot_range <= 1, f"distill robot_range must be in [0, 1], got {self.robot_range}")
        require(0 <= self.rough_fraction <= 1, f"distill rough_fraction must be in [0, 1], got {self.rough_fraction}")
        require(0 <= self.push_speed <= 3, f"distill push_speed must be in [0, 3] m/s, got {self.push_speed}")
        require(0 <= self.noise <= 1, f"distill noise must be a factor in [0, 1] of Table II's, got {self.noise}")
        require(self.rollout_seconds > 0, f"distill rollout_seconds must be > 0, got {self.rollout_seconds}")
        require(0 <= self.expert_share_until <= 1, f"expert_share_until must be in [0, 1], got {self.expert_share_until}")
        require(self.action_noise >= 0, f"distill action_noise must be >= 0, got {self.action_noise}")
        require(self.buffer_samples >= self.batch_size >= 1, "distill needs buffer_samples >= batch_size >= 1")
        require(self.updates_per_iteration >= 1, "distill updates_per_iteration must be >= 1")
        require(self.learning_rate > 0 and self.final_learning_rate > 0, "distill learning rates must be > 0")
        require(self.finetune_std > 0, f"finetune_std must be > 0, got {self.finetune_std}")
        require(self.finetune_learning_rate > 0, f"finetune_learning_rate must be > 0, got {self.finetune_learning_rate}")
        require(self.critic_warmup_iterations >= 0, "critic_warmup_iterations must be >= 0")
        require(self.anchor_updates >= 0, f"anchor_updates must be >= 0, got {self.anchor_updates}")
        require(self.anchor_learning_rate > 0, f"anchor_learning_rate must be > 0, got {self.anchor_learning_rate}")
        require(0 <= self.finetune_randomization <= 1,
                f"finetune_randomization must be a width in [0, 1] of Table II's, got {self.finetune_randomization}")
        require(self.finetune in ("full", "residual"), f"finetune must be 'full' or 'residual', got '{self.finetune}'")
        require(len(self.residual_dims) == len(PPOConfig().hidden_dims) and all(d > 0 for d in self.residual_dims),
                f"residual_dims must be {len(PPOConfig().hidden_dims)} positive widths, got {self.residual_dims}")
        require(self.pace in ("clock", "adaptive"), f"pace must be 'clock' or 'adaptive', got '{self.pace}'")
        require(0 < self.adaptive_step <= 1, f"adaptive_step must be in (0, 1], got {self.adaptive_step}")
        require(self.adaptive_fall_rate > 0, f"adaptive_fall_rate must be > 0 falls per second, got {self.adaptive_fall_rate}")
        require(0 <= self.finetune_noise <= 1, f"finetune_noise must be a factor in [0, 1] of Table II's, got {self.finetune_noise}")

    def steps_per_env(self, dt: float) -> int:
        return max(1, round(self.rollout_seconds / dt))

    def expert_share(self, progress: float) -> float:
        """The expert's share of the executed action at stage progress in [0, 1]."""
        if self.expert_share_until <= 0:
            return 0.0
        return max(0.0, 1.0 - progress / self.expert_share_until)

    def learning_rate_at(self, progress: float) -> float:
        p = min(max(progress, 0.0), 1.0)
        return self.learning_rate + (self.final_learning_rate - self.learning_rate) * p

    def student_ppo(self, ppo: PPOConfig | None = None) -> PPOConfig:
        """The distilled actor's settings: those of plain PPO with a small initial action noise and
        learning rate."""
        return dataclasses.replace(ppo or PPOConfig(), init_std=self.finetune_std,
                                   learning_rate=self.finetune_learning_rate)

    def finetune_ppo(self, ppo: PPOConfig | None = None) -> PPOConfig:
        """PPO settings of the fine-tuning stage: the student's, its hidden layers widened by the
        residual units when `finetune` is "residual"."""
        student = self.student_ppo(ppo)
        if self.finetune == "full":
            return student
        from opt2skill.rl.residual import widened

        return dataclasses.replace(student, hidden_dims=widened(student.hidden_dims, self.residual_dims))


def distillation_tracking_config(config: TrackingConfig, distill: DistillConfig) -> TrackingConfig:
    """The task's config with Table II narrowed to what the expert tolerates (observation noise is set
    by the stage through the curriculum's noise factor)."""
    r = config.randomization
    narrowed = {}
    for name in ROBOT_SIDE:
        lo, hi = getattr(r, name)
        narrowed[name] = (1 + distill.robot_range * (lo - 1), 1 + distill.robot_range * (hi - 1))
    randomization = dataclasses.replace(
        r, delay=(max(r.delay[0], distill.delay[0]), min(r.delay[1], distill.delay[1])),
        friction_scale=(max(r.friction_scale[0], distill.friction_scale[0]), min(r.friction_scale[1], distill.friction_scale[1])),
        rough_fraction=min(r.rough_fraction, distill.rough_fraction), push_speed=min(r.push_speed, distill.push_speed),
        **narrowed,
    )
    return dataclasses.replace(config, randomization=randomization)


def finetune_tracking_config(config: TrackingConfig, distill: DistillConfig) -> TrackingConfig:
    """The task's config for the PPO stage: Table II's randomization, its width rising over the
    curriculum from `finetune_randomization`; the observation noise scaled by `finetune_noise`, its
    curriculum starting from the noise the actor was distilled under (not from 0: a drop the actor
    never saw, then a rise it was not ready for, docs/distill.md)."""
    obs, curriculum = config.observations, config.curriculum
    scale = distill.finetune_noise
    noise = dataclasses.replace(obs.noise, **{f.name: scale * getattr(obs.noise, f.name) for f in dataclasses.fields(obs.noise)})
    start = min(1.0, max(curriculum.noise_start, distill.noise / scale)) if scale > 0 else 0.0
    return dataclasses.replace(config, observations=dataclasses.replace(obs, noise=noise),
                               curriculum=dataclasses.replace(curriculum, noise_start=start,
                                                              randomization_start=distill.finetune_randomization))
