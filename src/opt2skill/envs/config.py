"""The tracking task's one config: every setting of Section III-B, Tables I and II, with defaults.

Per-task differences (walking drops the base-position reward, Table I's note) and the ablations of
Section IV-C (Pos, Pos+F, Pos+T, Pos+F+T) are values of this config, made by `tracking_config`;
nothing else varies the environment. docs/envs.md explains each value.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from opt2skill.errors import ConfigError

ABLATIONS = {  # name -> (reference contact forces, reference joint torques): observation and reward
    "pos": (False, False),
    "pos_f": (True, False),
    "pos_t": (False, True),
    "pos_f_t": (True, True),
}
KERNELS = ("exp_sq", "exp_l1", "sq")
SAMPLINGS = ("uniform", "adaptive")  # EpisodeConfig.sampling


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)


@dataclass(frozen=True)
class Term:
    """One reward term: `weight * kernel(error)`.

    exp_sq: exp(-scale |e|_2^2); exp_l1: exp(-scale |e|_1); sq: |e|_2^2 (penalties, negative weight).
    A weight of 0 switches the term off (not computed, logged as 0).
    """

    weight: float
    scale: float = 0.0
    kernel: str = "exp_sq"

    def check(self, name: str) -> None:
        _require(self.kernel in KERNELS, f"reward '{name}': kernel must be one of {KERNELS}, got '{self.kernel}'")
        _require(math.isfinite(self.weight) and math.isfinite(self.scale),
                 f"reward '{name}': weight and scale must be finite numbers, got {self.weight} and {self.scale}")
        _require(self.scale >= 0, f"reward '{name}': scale must be >= 0, got {self.scale}")
        if self.kernel == "sq":
            _require(self.weight <= 0, f"penalty '{name}' must have a weight <= 0, got {self.weight}")
        else:
            _require(self.weight >= 0, f"reward '{name}' must have a weight >= 0, got {self.weight}")


@dataclass(frozen=True)
class RewardConfig:
    """Table I. Task terms compare the post-step state with the reference (docs/envs.md, alignment)."""

    joint_pos: Term = Term(0.3, 5.0)
    base_pos: Term = Term(0.3, 20.0)
    base_ori: Term = Term(0.3, 50.0)  # rotation vector of q_ref^-1 q (geometry.quat_error)
    base_lin_vel: Term = Term(0.3, 2.0)  # body frame
    base_ang_vel: Term = Term(0.3, 0.5)  # body frame
    ee_pos: Term = Term(0.3, 20.0)  # torso-relative, base frame, ObservationConfig.end_effectors
    joint_torque: Term = Term(0.1, 0.01)
    contact_force: Term = Term(0.1, 0.05, "exp_l1")  # foot forces, world axes
    action_rate: Term = Term(-0.05, kernel="sq")  # second difference a_t - 2 a_{t-1} + a_{t-2}
    torque: Term = Term(-0.03, kernel="sq")  # u / u_limit (the world's effective limit)
    joint_acc: Term = Term(-1e-6, kernel="sq")  # rad/s^2, mean over the policy step

    def terms(self) -> dict[str, Term]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def check(self) -> None:
        for name, term in self.terms().items():
            term.check(name)


@dataclass(frozen=True)
class NoiseConfig:
    """Table II observation noise: additive Gaussian standard deviations (actor only)."""

    joint_pos: float = 0.0875  # rad
    joint_vel: float = 0.075  # rad/s
    base_lin_vel: float = 0.15  # m/s
    base_ang_vel: float = 0.15  # rad/s
    gravity: float = 0.075  # projected gravity (unit vector)
    # The least share of these deviations a world reads with: each world draws its share uniformly in
    # [per_world_min, 1] at every reset. 1 (the paper): every world at full noise, so the policy never
    # meets the noise-free world it is evaluated in and deployed to (docs/experiments.md: its pace
    # follows the joint-position noise). Below 1 is an addition to the paper.
    per_world_min: float = 1.0

    def check(self) -> None:
        for f in dataclasses.fields(self):
            _require(getattr(self, f.name) >= 0, f"noise '{f.name}' must be >= 0")
        _require(self.per_world_min <= 1, f"noise per_world_min must be in [0, 1], got {self.per_world_min}")


@dataclass(frozen=True)
class ObservationConfig:
    """Section III-B observations. Layouts: `envs.observations.layout` and docs/envs.md."""

    history: int = 10  # N samples of joint positions and actions (0, 5, 10, 15 in the paper's ablation)
    stride: int = 4  # policy steps between history samples (50 Hz at 200 Hz)
    reference_force: bool = True  # reference contact forces observed and rewarded (Pos+F)
    reference_torque: bool = True  # reference joint torques observed and rewarded (Pos+T)
    # Reference frame given with the observation at step t, relative to t, for kinematic quantities
    # (positions, velocities, end effectors): 1 = the frame the step's result is scored against.
    # Torques and contact forces are always those of frame t (applied over [t, t + dt)).
    reference_offset: int = 1
    end_effectors: tuple[str, ...] = ("left_hand", "right_hand", "left_foot", "right_foot")
    noise: NoiseConfig = field(default_factory=NoiseConfig)

    def check(self) -> None:
        _require(0 <= self.history <= 50, f"history must be in [0, 50] samples, got {self.history}")
        _require(1 <= self.stride <= 50, f"history stride must be in [1, 50] policy steps, got {self.stride}")
        _require(self.reference_offset in (0, 1), f"reference_offset must be 0 or 1, got {self.reference_offset}")
        _require(len(self.end_effectors) > 0, "at least one end effector must be tracked")
        self.noise.check()


@dataclass(frozen=True)
class ActionConfig:
    """PD targets = default pose + scale * action (docs/envs.md explains the scale)."""

    scale: float = 0.5  # rad per action unit
    clip: float = 10.0  # actions are clipped to [-clip, clip] before scaling (runaway samples)
    # The servos' stiffness for this policy: the robot file's Kp times kp_scale (Kd unchanged), in
    # training, evaluation and the exported metadata. A softer servo passes less of a joint reading's
    # error into torque (a target that follows the read position moves the torque by Kp times it).
    kp_scale: float = 1.0

    def check(self) -> None:
        _require(0 < self.scale <= 5, f"action scale must be in (0, 5] rad, got {self.scale}")
        _require(0.05 <= self.kp_scale <= 2, f"kp_scale must be in [0.05, 2], got {self.kp_scale}")
        _require(self.clip > 0, f"action clip must be > 0, got {self.clip}")


@dataclass(frozen=True)
class TerminationConfig:
    """An episode ends at the reference's last frame (a time-out, bootstrapped), or when one of these
    thresholds is exceeded after a step (0 switches a threshold off), or when the world's physics
    diverged (`sim` flags it unstable)."""

    max_height_error: float = 0.25  # m, |base z - reference base z|
    max_orientation_error: float = 0.8  # rad, geodesic angle between base and reference orientation
    max_xy_error: float = 0.5  # m, horizontal base position error (a robot left behind by a walking reference)
    min_height: float = 0.4  # m, base height above the world's start level: a fall
    # m, a free prop's (a box's) distance from its reference position: a dropped or pushed box
    max_prop_error: float = 0.15

    def check(self) -> None:
        for f in dataclasses.fields(self):
            _require(getattr(self, f.name) >= 0, f"termination '{f.name}' must be >= 0 (0: off)")


@dataclass(frozen=True)
class RandomizationConfig:
    """Table II, re-sampled at every reset of a world. Ranges are (low, high) factors unless noted."""

    enabled: bool = True
    delay: tuple[float, float] = (0.0, 0.02)  # s, action delay
    motor_strength: tuple[float, float] = (0.95, 1.05)  # per joint: Kp, Kd and the torque limit
    kp_factor: tuple[float, float] = (0.9, 1.1)  # per joint
    kd_factor: tuple[float, float] = (0.9, 1.1)  # per joint
    mass_scale: tuple[float, float] = (0.9, 1.1)  # per link, mass and inertia
    gravity_scale: tuple[float, float] = (0.9, 1.1)
    friction_scale: tuple[float, float] = (0.3, 1.0)
    rough_fraction: float = 0.5  # share of resets on rough terrain (Table II: flat, rough)
    rough_amplitude: float = 0.02  # m, heights uniform in [-a, a]
    rough_cell: float = 0.4  # m, lattice of random heights (interpolated on the 0.2 m grid)
    rough_variants: int = 4  # distinct rough terrains (seeded)
    # External disturbances (Section III-B names them beside Table II): every `push_interval` seconds
    # (uniform) a world's base gets a horizontal velocity change of uniform direction and a speed
    # uniform in [0, push_speed] m/s. 0 switches pushes off.
    push_speed: float = 0.3  # m/s
    push_interval: tuple[float, float] = (2.0, 6.0)  # s

    RANGES = ("delay", "motor_strength", "kp_factor", "kd_factor", "mass_scale", "gravity_scale", "friction_scale")

    def ranges(self) -> dict[str, tuple[float, float]]:
        return {name: getattr(self, name) for name in self.RANGES}

    def narrowed(self, width: float) -> RandomizationConfig:
        """These ranges shrunk toward the nominal world (no delay, factors of 1) to `width` in [0, 1] of
        their size, and the rough share with them: the curriculum's randomization at a given factor."""
        if width >= 1:
            return self

        def toward_nominal(name: str) -> tuple[float, float]:
            nominal = 0.0 if name == "delay" else 1.0
            lo, hi = getattr(self, name)
            return nominal + width * (lo - nominal), nominal + width * (hi - nominal)

        return dataclasses.replace(self, rough_fraction=width * self.rough_fraction, push_speed=width * self.push_speed,
                                   **{name: toward_nominal(name) for name in self.RANGES})

    def check(self) -> None:
        for name, (lo, hi) in self.ranges().items():
            _require(0 <= lo <= hi, f"randomization '{name}' must be a range 0 <= low <= high, got ({lo}, {hi})")
        _require(self.delay[1] <= 0.02 + 1e-12, f"action delay must be at most 0.02 s (the sim's max_delay), got {self.delay[1]}")
        _require(0 <= self.rough_fraction <= 1, f"rough_fraction must be in [0, 1], got {self.rough_fraction}")
        _require(0 <= self.rough_amplitude <= 0.1, f"rough_amplitude must be in [0, 0.1] m, got {self.rough_amplitude}")
        _require(0.2 <= self.rough_cell <= 5, f"rough_cell must be in [0.2, 5] m, got {self.rough_cell}")
        _require(1 <= self.rough_variants <= 32, f"rough_variants must be in [1, 32], got {self.rough_variants}")
        _require(0 <= self.push_speed <= 3, f"push_speed must be in [0, 3] m/s, got {self.push_speed}")
        lo, hi = self.push_interval
        _require(0.05 <= lo <= hi, f"push_interval must be a range 0.05 <= low <= high seconds, got ({lo}, {hi})")


@dataclass(frozen=True)
class CurriculumConfig:
    """Noise curriculum (Section III-B): observation noise and penalty weights are multiplied by a
    factor rising linearly from `*_start` to 1 while training progress goes from `ramp[0]` to `ramp[1]`
    (progress = env steps done / env steps planned, told by the runner).

    The width of Table II's ranges can follow the same ramp (`randomization_start` < 1, an addition to
    the paper, which randomizes in full from the start): the PPO stage after distillation starts near
    the conditions the actor was distilled under (docs/distill.md)."""

    noise_start: float = 0.0
    penalty_start: float = 0.1
    randomization_start: float = 1.0
    ramp: tuple[float, float] = (0.1, 0.6)

    def check(self) -> None:
        starts = (self.noise_start, self.penalty_start, self.randomization_start)
        _require(all(0 <= s <= 1 for s in starts), f"curriculum start factors must be in [0, 1], got {starts}")
        _require(0 <= self.ramp[0] <= self.ramp[1] <= 1, f"curriculum ramp must satisfy 0 <= start <= end <= 1, got {self.ramp}")

    def _rise(self, start: float, progress: float) -> float:
        lo, hi = self.ramp
        x = 1.0 if hi <= lo else min(max((progress - lo) / (hi - lo), 0.0), 1.0)
        return start + (1 - start) * x

    def factors(self, progress: float) -> tuple[float, float]:
        """(noise factor, penalty factor) at training progress in [0, 1]."""
        return self._rise(self.noise_start, progress), self._rise(self.penalty_start, progress)

    def randomization_width(self, progress: float) -> float:
        """The fraction of Table II's range widths drawn from at training progress in [0, 1]."""
        return self._rise(self.randomization_start, progress)


@dataclass(frozen=True)
class EpisodeConfig:
    """How episodes start: a trajectory uniformly at random, a start frame uniformly in [0, T - 2]
    (or 0 with probability `start_at_zero`); or, with `sampling="adaptive"`, weighted toward the
    parts of the references where worlds fail (envs/start_sampling.py)."""

    start_at_zero: float = 0.0
    sampling: str = "uniform"  # or "adaptive"
    bin_seconds: float = 0.5  # adaptive: length of a start bin
    lookback_seconds: float = 1.0  # adaptive: a failure also weights the bins this far before it
    uniform_share: float = 0.3  # adaptive: share of starts still drawn uniformly
    half_life: float = 500.0  # adaptive: finished episodes over which the failure scores halve

    def check(self) -> None:
        _require(0 <= self.start_at_zero <= 1, f"start_at_zero must be a probability, got {self.start_at_zero}")
        _require(self.sampling in SAMPLINGS, f"episode sampling must be one of {', '.join(SAMPLINGS)}, got '{self.sampling}'")
        _require(self.bin_seconds > 0, f"episode bin_seconds must be > 0, got {self.bin_seconds}")
        _require(self.lookback_seconds >= 0, f"episode lookback_seconds must be >= 0, got {self.lookback_seconds}")
        _require(0 <= self.uniform_share <= 1, f"episode uniform_share must be in [0, 1], got {self.uniform_share}")
        _require(self.half_life > 0, f"episode half_life must be > 0 episodes, got {self.half_life}")


@dataclass(frozen=True)
class TrackingConfig:
    task: str = ""  # the dataset's task; decides per-task defaults (tracking_config)
    ablation: str = "pos_f_t"
    observations: ObservationConfig = field(default_factory=ObservationConfig)
    actions: ActionConfig = field(default_factory=ActionConfig)
    rewards: RewardConfig = field(default_factory=RewardConfig)
    terminations: TerminationConfig = field(default_factory=TerminationConfig)
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    episodes: EpisodeConfig = field(default_factory=EpisodeConfig)

    def check(self) -> None:
        _require(self.ablation in ABLATIONS, f"ablation must be one of {', '.join(ABLATIONS)}, got '{self.ablation}'")
        force, torque = ABLATIONS[self.ablation]
        obs = self.observations
        _require(
            (obs.reference_force, obs.reference_torque) == (force, torque),
            f"ablation '{self.ablation}' needs reference_force={force}, reference_torque={torque}",
        )
        _require(
            (self.rewards.contact_force.weight > 0) <= force and (self.rewards.joint_torque.weight > 0) <= torque,
            f"ablation '{self.ablation}' switches off the contact-force or torque reward",
        )
        for part in (obs, self.actions, self.rewards, self.terminations, self.randomization, self.curriculum, self.episodes):
            part.check()


def check_reference_inputs(ablation: str, has_dynamics: bool, source: str = "to") -> None:
    """Kinematic references (IK, human motion) have no torques or contact forces: only `pos` can use them.

    Refused rather than switched silently: the ablation is part of a checkpoint's identity.
    """
    force, torque = ABLATIONS.get(ablation, (False, False))
    if not has_dynamics and (force or torque):
        raise ConfigError(
            f"these references are kinematic (source '{source}', has_dynamics=False: no joint torques or contact "
            f"forces), so ablation '{ablation}' cannot observe or reward them; train with --ablation pos"
        )


# Whether the base-position reward applies: as the task registers it (Table I: not for walking), or
# switched on or off against that (a deviation from the paper, recorded in the run's config).
BASE_POSITION = ("task", "on", "off")


def parse_reward(text: str) -> tuple[str, float, float | None]:
    """'NAME=WEIGHT' or 'NAME=WEIGHT:SCALE' (`train --reward`) as (name, weight, scale or None)."""
    name, sep, value = text.partition("=")
    weight, _, scale = value.partition(":")
    try:
        if not (sep and name.strip() and weight.strip()):
            raise ValueError
        return name.strip(), float(weight), float(scale) if scale.strip() else None
    except ValueError:
        raise ConfigError(f"--reward expects NAME=WEIGHT or NAME=WEIGHT:SCALE (e.g. base_lin_vel=0.3:8), "
                          f"got '{text}'") from None


def with_rewards(rewards: RewardConfig, changes: tuple[tuple[str, float, float | None], ...], force: bool = True,
                 torque: bool = True) -> RewardConfig:
    """Table I's terms with `changes` ((name, weight, scale or None: the term's own)) applied: a deviation
    from the paper, recorded with the run's config. A force or torque term needs those inputs."""
    terms = rewards.terms()
    for name, weight, scale in changes:
        if name not in terms:
            raise ConfigError(f"--reward: unknown term '{name}'; terms: {', '.join(terms)}")
        if weight != 0 and ((name == "contact_force" and not force) or (name == "joint_torque" and not torque)):
            raise ConfigError(f"--reward {name}: this ablation has no reference {name.replace('_', ' ')}s to "
                              "reward (use --ablation pos_f_t, or pos_f / pos_t)")
        term = dataclasses.replace(terms[name], weight=weight, scale=terms[name].scale if scale is None else scale)
        term.check(name)
        terms[name] = term
    return RewardConfig(**terms)


def tracking_config(task: str = "", ablation: str = "pos_f_t", history: int = 10, kp_scale: float = 1.0,
                    sampling: str = "uniform", base_position: str = "task",
                    rewards_changed: tuple[tuple[str, float, float | None], ...] = (),
                    noise_min: float = 1.0) -> TrackingConfig:
    """The defaults for a dataset of `task`, with an ablation, a history length, a servo stiffness,
    the episodes' start sampling, the base-position reward's choice (BASE_POSITION), any reward
    terms' weights and scales (`with_rewards`) and the least share of observation noise a world
    trains with (`NoiseConfig.per_world_min`) applied, in that order."""
    if ablation not in ABLATIONS:
        raise ConfigError(f"ablation must be one of {', '.join(ABLATIONS)}, got '{ablation}'")
    if base_position not in BASE_POSITION:
        raise ConfigError(f"base position must be one of {', '.join(BASE_POSITION)}, got '{base_position}'")
    force, torque = ABLATIONS[ablation]
    rewards = RewardConfig()
    tracked = _tracks_base_position(task) if task and base_position == "task" else base_position != "off"
    if not tracked:
        rewards = dataclasses.replace(rewards, base_pos=dataclasses.replace(rewards.base_pos, weight=0.0))
    rewards = dataclasses.replace(
        rewards,
        contact_force=rewards.contact_force if force else dataclasses.replace(rewards.contact_force, weight=0.0),
        joint_torque=rewards.joint_torque if torque else dataclasses.replace(rewards.joint_torque, weight=0.0),
    )
    rewards = with_rewards(rewards, rewards_changed, force, torque)
    observations = ObservationConfig(history=history, reference_force=force, reference_torque=torque,
                                     noise=NoiseConfig(per_world_min=noise_min))
    config = TrackingConfig(task=task, ablation=ablation, observations=observations, rewards=rewards,
                            actions=ActionConfig(kp_scale=kp_scale), episodes=EpisodeConfig(sampling=sampling))
    config.check()
    return config


def _tracks_base_position(task: str) -> bool:
    """The task's registration says whether the base-position reward applies (Table I); motions of
    no registered task (recorded, retargeted) track it."""
    from opt2skill.tasks import available_tasks, task_info

    return task not in available_tasks() or task_info(task).track_base_position


def nominal_ranges(randomization: RandomizationConfig) -> dict:
    """Table II's ranges collapsed to the nominal world (no delay, factors of 1, flat ground)."""
    ranges = {name: ((0.0, 0.0) if name == "delay" else (1.0, 1.0)) for name in randomization.RANGES}
    return {**ranges, "rough_fraction": 0.0}


def evaluation_config(config: TrackingConfig, randomize: bool = False, noise: bool = False,
                      pushes: bool = False) -> TrackingConfig:
    """The same task for evaluation: randomization (Table II), pushes and observation noise off unless
    asked for, every episode from frame 0, the curriculum at its end."""
    randomization = config.randomization
    return dataclasses.replace(
        config,
        randomization=dataclasses.replace(randomization, enabled=randomize or pushes,
                                          push_speed=randomization.push_speed if pushes else 0.0,
                                          **({} if randomize else nominal_ranges(randomization))),
        observations=dataclasses.replace(  # noise: Table II's in full in every world, or none
            config.observations, noise=dataclasses.replace(config.observations.noise, per_world_min=1.0) if noise
            else NoiseConfig(0.0, 0.0, 0.0, 0.0, 0.0)),
        episodes=dataclasses.replace(config.episodes, start_at_zero=1.0, sampling="uniform"),
    )
