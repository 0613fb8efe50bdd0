"""Strided histories of per-world vectors: N samples taken every `stride` pushes, newest first.

All worlds push together once per policy step, so one ring buffer with one write position serves
every world and reading the history is one gather of N rows. A reset fills a world's whole ring
with its reset value, so its history reads as if the robot had been held there.
"""

from __future__ import annotations

import numpy as np


class StridedHistory:
    def __init__(self, nworld: int, dim: int, samples: int, stride: int, dtype=np.float64):
        self.samples, self.stride, self.dim = samples, stride, dim
        self.depth = max((samples - 1) * stride + 1, 1)  # pushes a full history spans
        self._ring = np.zeros((nworld, self.depth, dim), dtype=dtype)
        self._head = 0  # ring index of the newest sample
        self._offsets = np.arange(samples) * stride  # newest first

    def push(self, values: np.ndarray) -> None:
        """Append the newest sample of every world (nworld, dim)."""
        self._head = (self._head + 1) % self.depth
        self._ring[:, self._head] = values

    def reset(self, worlds: np.ndarray, values: np.ndarray) -> None:
        """Fill the whole history of `worlds` (k,) with their values: (k, dim) repeated, or one per
        ring slot (k, depth, dim) (e.g. independently noisy readings of the same state)."""
        self._ring[worlds] = values[:, None, :] if values.ndim == 2 else values

    def newest(self, back: int = 0) -> np.ndarray:
        """The sample pushed `back` pushes ago (nworld, dim); back < depth."""
        return self._ring[:, (self._head - back) % self.depth]

    def read(self) -> np.ndarray:
        """(nworld, samples * dim): [x_t, x_{t-stride}, ..., x_{t-(N-1) stride}] per world."""
        index = (self._head - self._offsets) % self.depth
        return self._ring[:, index].reshape(len(self._ring), self.samples * self.dim)
