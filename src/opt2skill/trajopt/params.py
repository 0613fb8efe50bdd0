"""Task parameters: each has an allowed range (physics, hard) and a sampling range (configurable).

Sampling is uniform and seeded per trajectory: parameters of trajectory `index` depend only on
(`seed`, `index`), so a resumed or reordered generation samples exactly the same values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from opt2skill.errors import ConfigError


@dataclass(frozen=True)
class Param:
    name: str
    allowed: tuple[float, float]  # any value outside is an error
    default_range: tuple[float, float]  # sampled when the user gives no range
    unit: str
    help: str


class ParamSpace:
    """Ordered parameters with their sampling ranges (defaults overridden by `ranges`)."""

    def __init__(self, params: list[Param], ranges: dict[str, tuple[float, float]] | None = None):
        self.params = {p.name: p for p in params}
        self.ranges = {p.name: tuple(map(float, p.default_range)) for p in params}
        for name, bounds in (ranges or {}).items():
            self.set_range(name, bounds)

    def set_range(self, name: str, bounds: tuple[float, float]) -> None:
        param = self._get(name)
        lo, hi = (float(b) for b in bounds)
        if lo > hi:
            raise ConfigError(f"range of '{name}' is empty: [{lo:g}, {hi:g}]")
        for value in (lo, hi):
            self._check_one(param, value)
        self.ranges[name] = (lo, hi)

    def sample(self, seed: int, index: int) -> dict[str, float]:
        rng = np.random.default_rng([int(seed), int(index)])
        return {name: float(rng.uniform(lo, hi)) if hi > lo else lo for name, (lo, hi) in self.ranges.items()}

    def check(self, values: dict[str, float]) -> dict[str, float]:
        """All parameters present, known and allowed; returns them as floats in the space's order."""
        unknown = sorted(set(values) - set(self.params))
        if unknown:
            raise ConfigError(f"unknown parameters {unknown}; parameters: {', '.join(self.params)}")
        missing = [name for name in self.params if name not in values]
        if missing:
            raise ConfigError(f"missing parameters {missing}")
        checked = {}
        for name, param in self.params.items():
            value = float(values[name])
            self._check_one(param, value)
            checked[name] = value
        return checked

    def _get(self, name: str) -> Param:
        if name not in self.params:
            raise ConfigError(f"unknown parameter '{name}'; parameters: {', '.join(self.params)}")
        return self.params[name]

    @staticmethod
    def _check_one(param: Param, value: float) -> None:
        lo, hi = param.allowed
        if not (np.isfinite(value) and lo <= value <= hi):
            raise ConfigError(
                f"parameter '{param.name}' = {value:g} {param.unit} is outside its allowed range "
                f"[{lo:g}, {hi:g}] {param.unit}"
            )
