"""The tracking task (Section III-B): reference sampling, observations, rewards, terminations,
domain randomization and the noise curriculum, batched over N simulated worlds (docs/envs.md)."""

from opt2skill.envs.config import ABLATIONS, TrackingConfig, evaluation_config, tracking_config
from opt2skill.envs.env import CAUSES, Episodes, StepResult, TrackingEnv
from opt2skill.envs.observations import ObservationLayout, layout
from opt2skill.envs.reference import ReferenceBank

__all__ = [
    "ABLATIONS",
    "CAUSES",
    "Episodes",
    "ObservationLayout",
    "ReferenceBank",
    "StepResult",
    "TrackingConfig",
    "TrackingEnv",
    "evaluation_config",
    "layout",
    "tracking_config",
]
