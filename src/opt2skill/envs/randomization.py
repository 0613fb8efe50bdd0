"""Table II domain randomization: the worlds' physical parameters and terrain, drawn at every reset.

Everything physical reaches the simulator through `WorldParams` (docs/sim.md says how each field is
applied); observation noise is added by the environment (`TrackingEnv`), scaled by the curriculum.

Each world stands on the ground its reference was made on (the reference's scene). Randomized ground
is drawn on top of that: a reference made on the flat floor may be tracked on one of the rough
variants instead (lifted onto it); a reference made on stairs or a slope keeps its own ground.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from opt2skill.envs.config import RandomizationConfig
from opt2skill.sim import Flat, Terrain, TerrainGrid, WorldParams, rough, sample_uniform

MARGIN = 3.0  # m of rough ground around the references' base paths
RESOLUTION = 0.2  # m, heightfield grid (docs/sim.md: 0.2 m keeps the physics near the plane's speed)


def terrains(config: RandomizationConfig, grounds: Sequence[Terrain], xy_range, seed: int) -> list[Terrain]:
    """The references' own grounds first, then, if some reference was made on the flat floor,
    `rough_variants` rough terrains covering the references' paths."""
    grounds = list(grounds)
    if not config.enabled or config.rough_fraction == 0 or not any(isinstance(g, Flat) for g in grounds):
        return grounds
    (x0, x1), (y0, y1) = xy_range

    def snap(lo: float, hi: float) -> tuple[float, float]:
        return float(np.floor((lo - MARGIN) / RESOLUTION) * RESOLUTION), float(np.ceil((hi + MARGIN) / RESOLUTION) * RESOLUTION)

    grid = TerrainGrid(x_range=snap(x0, x1), y_range=snap(y0, y1), resolution=RESOLUTION,
                       z_range=(-config.rough_amplitude - 0.01, config.rough_amplitude + 0.01))
    return grounds + [rough(grid, config.rough_amplitude, config.rough_cell, seed=seed * 1000 + i)
                      for i in range(config.rough_variants)]


def sample_params(rng: np.random.Generator, k: int, nbody: int, nu: int, config: RandomizationConfig,
                  variants: Sequence[int], ground: np.ndarray, made_on_flat: np.ndarray) -> WorldParams:
    """Parameters of k worlds being reset: every Table II range sampled independently (per joint and
    per link where the field has them). Each world stands on `ground` (k,), its reference's own
    terrain; one whose reference was `made_on_flat` (k,) is moved, with probability `rough_fraction`,
    to one of the terrain indices `variants`, and lifted onto it."""
    params = WorldParams.nominal(k, nbody, nu) if not config.enabled else sample_uniform(rng, k, nbody, nu,
                                                                                         config.ranges())
    params.terrain = np.asarray(ground, dtype=int).copy()
    params.lift = np.asarray(made_on_flat, dtype=bool).copy()
    if config.enabled and len(variants):
        on_rough = rng.random(k) < config.rough_fraction
        params.terrain = np.where(on_rough & params.lift, rng.choice(list(variants), k), params.terrain)
    return params
