"""How fast a training run's curriculum advances when it is not tied to the clock.

The paper's curriculum (noise, penalties, and here the width of Table II's ranges) rises with the
environment steps. After distillation that pace is a guess: widen too fast and PPO wrecks the
distilled actor (docs/distill.md), too slow and the budget ends before the world is Table II's.
`AdaptivePace` widens the world only while the policy copes with it: after every iteration whose
worlds fell (lost height, orientation or stable physics) less often than `max_fall_rate` per second
of experience, smoothed over about `horizon` iterations, the progress moves `step` on. Drifting off
the reference (`xy_error`) ends a training episode but is not a fall, and evaluation does not count
it either.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from opt2skill.envs import CAUSES

FAILURES = tuple(c for c in CAUSES if c not in ("time_out", "xy_error"))


@dataclass
class AdaptivePace:
    step: float  # progress added per iteration that qualifies
    max_fall_rate: float  # failures per world-second of experience
    horizon: int = 20  # iterations over which the failure rate is smoothed (exponentially)
    fall_rate: float | None = None  # the smoothed rate so far (None: no iteration seen)

    def advance(self, progress: float, figures: dict[str, float], world_seconds: float) -> float:
        """The progress after an iteration with `figures` (rl.vec_env's summary) over `world_seconds`
        of experience, all worlds together."""
        failures = sum(figures.get(f"terminations/{c}", 0.0) for c in FAILURES)
        rate = failures / max(world_seconds, 1e-9)
        alpha = 1.0 / self.horizon
        self.fall_rate = rate if self.fall_rate is None else (1 - alpha) * self.fall_rate + alpha * rate
        if self.fall_rate < self.max_fall_rate:
            return min(1.0, progress + self.step)
        return progress

    def state(self) -> dict[str, Any]:
        return {"fall_rate": self.fall_rate}

    def restore(self, state: dict[str, Any]) -> None:
        self.fall_rate = state.get("fall_rate")
