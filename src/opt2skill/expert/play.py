"""`opt2skill play --expert`: the optimizer's feedback expert on its own, scored like a policy.

The expert tracks chosen references of a dataset from frame 0 in the tracking environment, at the
policy rate and in the policy's action space (held PD targets, `EnvExpert`), under the evaluation
config (randomization and observation noise off unless asked; the expert never reads observations,
so noise only changes what an actor would have seen). Each tracked motion is scored with the
paper's metrics (`eval.metrics.tracking_errors`), the same as `opt2skill play RUN`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from opt2skill.data.reader import Dataset
from opt2skill.envs import ReferenceBank, TrackingEnv, evaluation_config, tracking_config
from opt2skill.envs.evaluation import TrackedMotion, track
from opt2skill.errors import ConfigError, DataError
from opt2skill.expert.acting import EnvExpert, ExpertConfig
from opt2skill.model import load_robot


@dataclass
class ExpertPlayResult:
    motions: list[TrackedMotion]
    errors: list[dict[str, float]]  # eval.metrics tracking errors per motion


def play_expert(dataset_dir: Path, n: int = 4, randomize: bool = False, seed: int = 0,
                config: ExpertConfig | None = None, threads: int | None = None) -> ExpertPlayResult:
    """Track the dataset's first `n` references with the expert; motions and their tracking errors."""
    from opt2skill.eval.metrics import tracking_errors

    if n < 1:
        raise ConfigError(f"--n must be >= 1, got {n}")
    dataset = Dataset.open(dataset_dir)
    if len(dataset) == 0:
        raise DataError(f"dataset {dataset_dir} has no accepted trajectories")
    robot = load_robot(dataset.identity.get("robot", "digit"))
    n = min(n, len(dataset))
    references = [dataset[i] for i in range(n)]
    env_config = evaluation_config(tracking_config(dataset.identity.get("task", "")), randomize=randomize)
    bank = ReferenceBank.from_trajectories(robot, references, env_config.observations.end_effectors)
    with TrackingEnv(robot, bank, env_config, n, seed=seed, threads=threads) as env:
        env.set_progress(1.0)
        motions = track(env, EnvExpert(env, references, config), np.arange(n))
    errors = [tracking_errors(references[m.position], m.record(robot, references[m.position]), fell=m.fell).as_dict()
              for m in motions]
    return ExpertPlayResult(motions, errors)
