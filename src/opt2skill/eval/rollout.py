"""Policy rollouts on chosen references, as trajectory records the metrics compare.

Each reference is tracked once from its first frame by one simulated world of the tracking
environment (`envs.evaluation.track`: deterministic actions, the environment's terminations; use
`envs.evaluation_config` for randomization and noise off), in batches of worlds. The tracked motion
becomes a record (`data.record.build_trajectory`) on the reference's 200 Hz frames, so
`metrics.tracking_errors` compares like with like.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.envs import ReferenceBank, TrackingEnv
from opt2skill.envs.config import TrackingConfig
from opt2skill.envs.evaluation import Policy, track
from opt2skill.eval.metrics import TrackingErrors, tracking_errors
from opt2skill.model.robot import Robot
from opt2skill.scene.terrain import Terrain
from opt2skill.sim import MujocoBatchedSim, SimConfig

MAX_WORLDS = 64  # worlds per batch


@dataclass
class Rollout:
    """One reference tracked once: the reference, what the robot did, and why it stopped."""

    reference: Trajectory
    tracked: Trajectory  # the reference's frames 0 .. steps; base height from the start level
    cause: str  # envs.CAUSES: "time_out" when the reference ended
    z_offset: float = 0.0  # height the world was lifted by to stand on its terrain

    @property
    def fell(self) -> bool:
        return self.cause != "time_out"

    @property
    def steps(self) -> int:
        return self.tracked.num_frames - 1

    @property
    def duration(self) -> float:
        return self.steps * FRAME_DT

    def errors(self) -> TrackingErrors:
        return tracking_errors(self.reference, self.tracked, fell=self.fell)


def rollout(robot: Robot, references: Sequence[Trajectory], policy: Policy, config: TrackingConfig,
            seed: int = 0, terrain: Terrain | None = None, threads: int | None = None,
            progress: Callable[[int], None] | None = None) -> list[Rollout]:
    """Track every reference with `policy` (observations -> actions, batched) under `config`.

    `terrain`: the ground of every world (default: the environment's own, flat without
    randomization). `progress(k)` is told of each policy step of each batch (k worlds stepped).
    """
    out: list[Rollout] = []
    for first in range(0, len(references), MAX_WORLDS):
        batch = list(references[first:first + MAX_WORLDS])
        bank = ReferenceBank.from_trajectories(robot, batch, config.observations.end_effectors)
        sim = None
        if terrain is not None:
            sim = MujocoBatchedSim(robot, len(batch), SimConfig(nsubstep=5, nthread=threads), terrains=[terrain])
        with TrackingEnv(robot, bank, config, len(batch), seed=seed + first, sim=sim, threads=threads) as env:
            env.set_progress(1.0)  # penalties at full weight (the rewards are not reported here)
            step = _counting(policy, progress, len(batch))
            motions = track(env, step, np.arange(len(batch)))
            z0 = env.sim.z_offset
        for w, motion in enumerate(motions):
            reference = batch[motion.position]
            out.append(Rollout(reference, motion.record(robot, reference), motion.cause, float(z0[w])))
    return out


def planned_steps(references: Sequence[Trajectory]) -> int:
    """World-steps `rollout` takes at most: each batch runs until its longest reference ends."""
    return sum(len(batch) * (max(t.num_frames for t in batch) - 1)
               for batch in (references[i:i + MAX_WORLDS] for i in range(0, len(references), MAX_WORLDS)))


def _counting(policy: Policy, progress: Callable[[int], None] | None, worlds: int) -> Policy:
    if progress is None:
        return policy

    def step(obs: np.ndarray) -> np.ndarray:
        progress(worlds)
        return policy(obs)

    return step
