"""Table II domain randomization: the worlds' physical parameters and terrain, drawn at every reset.

Everything physical reaches the simulator through `WorldParams` (docs/sim.md says how each field is
applied); observation noise is added by the environment (`TrackingEnv`), scaled by the curriculum.
"""

from __future__ import annotations

import numpy as np

from opt2skill.envs.config import RandomizationConfig
from opt2skill.sim import Flat, Terrain, TerrainGrid, WorldParams, flat, rough, sample_uniform

MARGIN = 3.0  # m of rough ground around the references' base paths
RESOLUTION = 0.2  # m, heightfield grid (docs/sim.md: 0.2 m keeps the physics near the plane's speed)


def terrains(config: RandomizationConfig, xy_range, seed: int) -> list[Terrain]:
    """Flat first, then `rough_variants` rough terrains covering the references' paths."""
    if not config.enabled or config.rough_fraction == 0:
        return [flat()]
    (x0, x1), (y0, y1) = xy_range

    def snap(lo: float, hi: float) -> tuple[float, float]:
        return float(np.floor((lo - MARGIN) / RESOLUTION) * RESOLUTION), float(np.ceil((hi + MARGIN) / RESOLUTION) * RESOLUTION)

    grid = TerrainGrid(x_range=snap(x0, x1), y_range=snap(y0, y1), resolution=RESOLUTION,
                       z_range=(-config.rough_amplitude - 0.01, config.rough_amplitude + 0.01))
    return [flat()] + [rough(grid, config.rough_amplitude, config.rough_cell, seed=seed * 1000 + i)
                       for i in range(config.rough_variants)]


def sample_params(rng: np.random.Generator, k: int, nbody: int, nu: int, config: RandomizationConfig,
                  terrain_list: list[Terrain]) -> WorldParams:
    """Parameters of k worlds being reset: every Table II range sampled independently (per joint and
    per link where the field has them); terrain rough with probability `rough_fraction`."""
    if not config.enabled:
        return WorldParams.nominal(k, nbody, nu)
    params = sample_uniform(rng, k, nbody, nu, config.ranges())
    rough_ids = [i for i, t in enumerate(terrain_list) if not isinstance(t, Flat)]
    if rough_ids:
        on_rough = rng.random(k) < config.rough_fraction
        params.terrain = np.where(on_rough, rng.choice(rough_ids, k), 0)
    return params
