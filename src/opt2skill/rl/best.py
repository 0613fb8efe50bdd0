"""Keep a run's best policy by held-out results, judged on a schedule while it trains (issue 13).

Success flickers between checkpoints (80-100 % on the same held-out walks, docs/distill.md), and the
newest checkpoint is not the best one. Every `every` iterations the trainer's current actor tracks
held-out references of another seed from frame 0 (deterministic actions, `eval.rollout`) under the
conditions that matter for deployment: Table II's full randomization and observation noise by
default (`eval.evaluate.eval_config`), pushes off. Each judgement is a line of RUN/heldout.jsonl; the
best one so far is copied to RUN/best/model.pt with RUN/best/best.json saying why.

Order: higher success first, then the higher share of frames tracked, then the lower sum of the
Table III errors relative to the paper's row (so one metric cannot hide another).
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from opt2skill.data.atomic import atomic_path, dumps, write_json
from opt2skill.data.record import Trajectory
from opt2skill.envs.config import TrackingConfig
from opt2skill.errors import ConfigError
from opt2skill.model.robot import Robot
from opt2skill.rl.checkpoint import best_path

JUDGEMENTS = "heldout.jsonl"
# Table III, Opt2Skill (walking): the errors a judgement reports, relative to the paper's row.
TABLE_III = {"E_ee_foot": 5.23, "E_joint": 0.03, "E_vel_x": 4.86, "E_pos_x": 1.14}
TABLE_III_UNITS = {"E_ee_foot": "cm", "E_joint": "rad", "E_vel_x": "cm/s", "E_pos_x": "%"}


@dataclass(frozen=True)
class JudgeConfig:
    every: int = 50  # iterations between judgements (and one at the end of each stage)
    n: int = 10  # held-out references
    randomize: bool = True  # Table II's full randomization
    noise: bool = True  # Table II's observation noise
    seed: int = 0

    def check(self) -> None:
        if self.every < 1:
            raise ConfigError(f"held-out judgement interval must be >= 1 iteration, got {self.every}")
        if self.n < 1:
            raise ConfigError(f"held-out judgement needs >= 1 reference, got {self.n}")


def score(judgement: dict[str, Any]) -> tuple[float, float, float]:
    """The order of judgements: larger is better."""
    values = [(judgement.get(k), v) for k, v in TABLE_III.items()]
    errors = [x / v for x, v in values if x is not None and np.isfinite(x)]  # NaN is stored as null
    return judgement["success"], judgement["tracked"], -float(sum(errors)) if errors else -np.inf


class HeldOutJudge:
    """Judges actors of one run on held-out references and keeps the best checkpoint."""

    def __init__(self, run: Path, robot: Robot, references: Sequence[Trajectory], tracking: TrackingConfig,
                 config: JudgeConfig = JudgeConfig(), threads: int | None = None):
        from opt2skill.eval.evaluate import eval_config

        config.check()
        self.run, self.robot, self.config, self.threads = Path(run), robot, config, threads
        self.references = list(references)[: config.n]
        self.env_config = eval_config(tracking, randomize=config.randomize, noise=config.noise)
        self.best = self._read_best()

    def _read_best(self) -> dict[str, Any] | None:
        info = best_path(self.run).with_name("best.json")
        return json.loads(info.read_text()) if info.is_file() and best_path(self.run).is_file() else None

    def due(self, iteration: int) -> bool:
        return iteration % self.config.every == 0

    def judge(self, policy: Callable[[np.ndarray], np.ndarray], checkpoint: Path, stage: str, iteration: int,
              env_steps: int, elapsed: float = 0.0) -> dict[str, Any]:
        """Track the held-out references with `policy` (the actor saved in `checkpoint`); log the
        judgement and keep the checkpoint as the best if it beats the best so far."""
        from opt2skill.eval.rollout import rollout

        start = time.perf_counter()
        rollouts = rollout(self.robot, self.references, policy, self.env_config, seed=self.config.seed,
                           threads=self.threads)
        errors = [r.errors() for r in rollouts]
        judgement: dict[str, Any] = {
            "stage": stage, "iteration": iteration, "env_steps": env_steps, "elapsed": elapsed,
            "checkpoint": str(checkpoint),
            "success": float(np.mean([not r.fell for r in rollouts])),
            "tracked": float(np.mean([r.steps / (r.reference.num_frames - 1) for r in rollouts])),
            "conditions": asdict(self.config),
        }
        for name in TABLE_III:
            values = [getattr(e, name) for e in errors if np.isfinite(getattr(e, name))]
            judgement[name] = float(np.mean(values)) if values else float("nan")
        judgement["seconds"] = time.perf_counter() - start
        judgement["best"] = self.best is None or score(judgement) > score(self.best)
        if judgement["best"]:
            self._keep(checkpoint, judgement)
        with open(self.run / JUDGEMENTS, "a") as f:
            f.write(dumps(judgement) + "\n")
        return judgement

    def _keep(self, checkpoint: Path, judgement: dict[str, Any]) -> None:
        target = best_path(self.run)
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(target) as tmp:
            shutil.copyfile(checkpoint, tmp)
        write_json(target.with_name("best.json"), judgement)
        self.best = judgement


def judge_actor(judge: HeldOutJudge, actor, checkpoint: Path, stage: str, iteration: int, env_steps: int,
                elapsed: float) -> dict[str, float]:
    """Judge a training actor (an rsl_rl MLPModel, left in the mode it was in); the logged figures."""
    from opt2skill.rl.policy import Policy

    training = actor.training
    policy = Policy(actor)  # a snapshot of the normalizer and the MLP (it sets the actor to eval mode)
    actor.train(training)
    return judged_figures(judge.judge(policy, checkpoint, stage, iteration, env_steps, elapsed))


def judged_figures(judgement: dict[str, Any]) -> dict[str, float]:
    """A judgement as logged scalars (TensorBoard, progress.jsonl)."""
    return {f"heldout/{k}": float(judgement[k]) for k in ("success", "tracked", *TABLE_III)}
