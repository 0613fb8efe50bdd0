"""Where episodes start: a reference and a start frame, uniformly or weighted toward where worlds fail.

Uniform sampling (the default) spends most experience on what the policy already does well: a
heavy box is lifted in one second of an eight-second reference, and a world that drops it starts
again anywhere. Adaptive sampling splits every reference into bins of `bin_seconds` and keeps a
failure score per bin: a world that fails (any termination but the reference's end) adds to the
bin it failed in and, with falling weight, to the `lookback_seconds` before it, where the policy
can still recover. A share `uniform_share` of starts stays uniform, so no part is forgotten, and the
scores halve every `half_life` finished episodes, so the weight follows the policy as it improves.
The idea is that of adaptive clip sampling in motion-tracking work (e.g. BeyondMimic, Liao et al.
2025, which samples start bins by smoothed failure rates); this is our own form of it.
"""

from __future__ import annotations

import numpy as np

from opt2skill.envs.config import EpisodeConfig


class StartSampler:
    """Start (trajectory, frame) pairs for `lengths` (frames of each reference) at `dt` s per frame."""

    def __init__(self, config: EpisodeConfig, lengths: np.ndarray, dt: float):
        config.check()
        self.config = config
        self.lengths = np.asarray(lengths, dtype=np.int64)
        self.adaptive = config.sampling == "adaptive"
        # Start frames of reference t are [0, T_t - 2] (at least one step to go), cut into bins.
        self.bin_frames = max(1, round(config.bin_seconds / dt))
        counts = -(-(self.lengths - 1) // self.bin_frames)  # ceil: bins per reference
        self.first_bin = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self.bin_traj = np.repeat(np.arange(len(self.lengths)), counts)
        self.bin_start = (np.arange(int(counts.sum())) - self.first_bin[self.bin_traj]) * self.bin_frames
        self.bin_end = np.minimum(self.bin_start + self.bin_frames, self.lengths[self.bin_traj] - 1)  # exclusive
        self.score = np.zeros(len(self.bin_traj))
        back = max(0, round(config.lookback_seconds / dt / self.bin_frames))
        self.kernel = 1.0 - np.arange(back + 1) / (back + 1)  # weight of the failing bin, then earlier ones

    @property
    def num_bins(self) -> int:
        return len(self.score)

    def frames(self, rng: np.random.Generator, traj: np.ndarray) -> np.ndarray:
        """Uniform start frames on the given references: [0, T - 2] (at least one step to go), or 0 with
        probability `start_at_zero`."""
        return self._at_zero(rng, rng.integers(0, self.lengths[traj] - 1))

    def sample(self, rng: np.random.Generator, k: int) -> tuple[np.ndarray, np.ndarray]:
        """k start pairs (trajectory indices, start frames)."""
        traj = rng.integers(0, len(self.lengths), k)
        total = self.score.sum()
        if not (self.adaptive and total > 0):
            return traj, self.frames(rng, traj)
        frames = rng.integers(0, self.lengths[traj] - 1)
        weighted = rng.random(k) >= self.config.uniform_share
        m = int(weighted.sum())
        if m:
            bins = rng.choice(self.num_bins, size=m, p=self.score / total)
            traj[weighted] = self.bin_traj[bins]
            frames[weighted] = rng.integers(self.bin_start[bins], self.bin_end[bins])
        return traj, self._at_zero(rng, frames)

    def _at_zero(self, rng: np.random.Generator, frames: np.ndarray) -> np.ndarray:
        p0 = self.config.start_at_zero
        return np.where(rng.random(len(frames)) < p0, 0, frames) if p0 > 0 else frames

    def record(self, traj: np.ndarray, frames: np.ndarray, failed: np.ndarray) -> None:
        """Episodes that ended on reference `traj` at frame `frames`; `failed`: not at the reference's end."""
        if not self.adaptive or len(traj) == 0:
            return
        self.score *= 0.5 ** (len(traj) / self.config.half_life)
        failed = np.asarray(failed, dtype=bool)
        for t, frame in zip(np.asarray(traj)[failed], np.asarray(frames)[failed]):
            own = min(int(frame), int(self.lengths[t]) - 2) // self.bin_frames
            for back, weight in enumerate(self.kernel):
                if own - back < 0:
                    break
                self.score[self.first_bin[t] + own - back] += weight

    def state(self) -> dict:
        """What a checkpoint keeps, so a resumed run samples where it left off."""
        return {"score": self.score.copy()}

    def restore(self, state: dict) -> None:
        score = np.asarray(state["score"], dtype=np.float64)
        if score.shape != self.score.shape:  # another dataset or bin size: start afresh, uniformly
            return
        self.score[:] = score

    def concentration(self) -> float:
        """Share of the weighted starts that fall in the top tenth of the bins (0 when nothing failed yet):
        how sharply the sampling focuses."""
        total = self.score.sum()
        if not self.adaptive or total <= 0:
            return 0.0
        top = max(1, self.num_bins // 10)
        return float(np.sort(self.score)[-top:].sum() / total)
