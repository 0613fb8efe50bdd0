"""Action delay per world, at physics-step resolution, as the control sequence of one policy step.

The policy sends PD targets once per policy step (S physics steps). With a delay of d physics
steps, physics step n (counted from a reset) applies the targets the policy sent at policy step
floor((n - d) / S), i.e. substep j of the current policy step uses the targets sent
ceil((d - j) / S) policy steps ago. Before a world's first targets exist, the first targets
stand in (as if the policy had been sending them all along), unless a reset gave initial targets.
Backend-independent: any simulator can feed `sequence()` to its physics.
"""

from __future__ import annotations

import numpy as np

from opt2skill.errors import ConfigError


class ActionDelay:
    def __init__(self, nworld: int, nu: int, nsubstep: int, max_delay: int):
        if max_delay < 0:
            raise ConfigError(f"maximum action delay must be >= 0 physics steps, got {max_delay}")
        self.nsubstep = nsubstep
        self.max_delay = max_delay
        self.depth = -(-max_delay // nsubstep) + 1  # policy steps of targets kept, newest first
        self._history = np.zeros((nworld, self.depth, nu))
        self._fresh = np.ones(nworld, dtype=bool)  # no targets yet: the next ones fill the history
        self._rows = np.arange(nworld)[:, None]
        self._delay = np.zeros(nworld, dtype=int)
        self._lag = np.zeros((nworld, nsubstep), dtype=int)
        self._substeps = np.arange(nsubstep)

    @property
    def delay(self) -> np.ndarray:
        return self._delay.copy()

    def set_delay(self, worlds: np.ndarray, delay: np.ndarray) -> None:
        """Delays in physics steps for the given worlds (set at reset; the history is kept)."""
        delay = np.asarray(delay, dtype=int)
        if delay.min(initial=0) < 0 or delay.max(initial=0) > self.max_delay:
            raise ConfigError(f"action delay must be in [0, {self.max_delay}] physics steps")
        self._delay[worlds] = delay
        self._lag[worlds] = -((self._substeps[None, :] - delay[:, None]) // self.nsubstep)

    def clear(self, worlds: np.ndarray, targets: np.ndarray | None = None) -> None:
        """Forget the worlds' past targets; `targets` (k, nu), if given, stand in for them."""
        if targets is None:
            self._fresh[worlds] = True
        else:
            self._history[worlds] = np.asarray(targets)[:, None, :]
            self._fresh[worlds] = False

    def sequence(self, targets: np.ndarray) -> np.ndarray:
        """Record this policy step's targets (nworld, nu); return the controls (nworld, S, nu)."""
        history = self._history
        history[:, 1:] = history[:, :-1]
        history[:, 0] = targets
        if self._fresh.any():
            history[self._fresh] = targets[self._fresh, None, :]
            self._fresh[:] = False
        return history[self._rows, self._lag]
