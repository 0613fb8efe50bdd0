"""Terrains: flat, rough (a heightfield), stairs and slopes (boxes), each with its height function.

A simulator holds a list of terrains and gives every world one of them (`WorldParams.terrain`).
Flat is MuJoCo's plane. Rough is a heightfield: MuJoCo collides with it as two triangles per cell,
split along the cell's (x0, y0)-(x1, y1) diagonal, and `Rough.height` interpolates the same way.
Stairs and slopes are boxes, so step edges are sharp and the feet get a few contacts each (a foot
on a heightfield gets up to 50, two per cell it covers, which is slow and, at fine resolution,
truncated unevenly). Stairs and slopes go up along +x from `start` (stairs can also go down: a
raised landing before `start`, then steps down); the plane is the ground before them and beside them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from opt2skill.errors import ConfigError


@dataclass(frozen=True)
class TerrainGrid:
    """Extent and resolution of the rough-terrain heightfield (world frame, metres).

    The default covers 20 m x 12 m around the start, enough for the walking references (up to about
    14 s at up to 1.5 m/s along x); outside it there is no ground. A foot gets up to two contacts per
    cell it covers: at 0.2 m about 3 (physics as fast as on the plane), at 0.1 m 7 to 12 (half the
    speed), at 0.05 m 24 (a third); docs/sim.md.
    `z_range` bounds every height the grid can hold; the heightfield's base sits at its lower end.
    """

    x_range: tuple[float, float] = (-4.0, 16.0)
    y_range: tuple[float, float] = (-6.0, 6.0)
    resolution: float = 0.2
    z_range: tuple[float, float] = (-0.2, 0.2)

    def __post_init__(self) -> None:
        for name in ("x_range", "y_range", "z_range"):
            lo, hi = getattr(self, name)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise ConfigError(f"terrain grid {name} must be an increasing pair of numbers, got ({lo}, {hi})")
        if not (0.01 <= self.resolution <= 1.0):
            raise ConfigError(f"terrain grid resolution must be in [0.01, 1] m, got {self.resolution}")
        if self.ncol * self.nrow > 1_000_000:
            raise ConfigError(
                f"terrain grid has {self.ncol * self.nrow} points (> 1e6); every world holds a copy: "
                "use a coarser resolution or a smaller extent"
            )

    @property
    def ncol(self) -> int:
        return int(round((self.x_range[1] - self.x_range[0]) / self.resolution)) + 1

    @property
    def nrow(self) -> int:
        return int(round((self.y_range[1] - self.y_range[0]) / self.resolution)) + 1

    @property
    def x(self) -> np.ndarray:
        return np.linspace(*self.x_range, self.ncol)

    @property
    def y(self) -> np.ndarray:
        return np.linspace(*self.y_range, self.nrow)

    @property
    def spacing(self) -> np.ndarray:
        """Actual (dx, dy) between grid points."""
        return np.array([np.diff(self.x_range)[0] / (self.ncol - 1), np.diff(self.y_range)[0] / (self.nrow - 1)])


@dataclass(frozen=True)
class Flat:
    """MuJoCo's plane at z = 0."""

    name: str = "flat"

    def height(self, xy: np.ndarray) -> np.ndarray:
        return np.zeros(np.shape(xy)[:-1])

    def max_height(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        return np.zeros(len(lo))


@dataclass(frozen=True, eq=False)
class Rough:
    """A heightfield on `grid`: heights (nrow, ncol) in metres, rows along y, columns along x."""

    grid: TerrainGrid
    heights: np.ndarray = field(repr=False)
    name: str = "rough"

    def __post_init__(self) -> None:
        if self.heights.shape != (self.grid.nrow, self.grid.ncol):
            raise ConfigError(f"terrain {self.name}: heights {self.heights.shape} do not match its grid")
        lo, hi = float(self.heights.min()), float(self.heights.max())
        if lo < self.grid.z_range[0] or hi > self.grid.z_range[1]:
            raise ConfigError(
                f"terrain {self.name} spans heights [{lo:.3f}, {hi:.3f}] m, outside its grid's z range "
                f"{self.grid.z_range}; widen TerrainGrid.z_range"
            )

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Surface height at xy (..., 2), as MuJoCo collides; outside the grid, its edge's height."""
        g, h = self.grid, self.heights
        f = np.clip((np.asarray(xy, dtype=float) - [g.x_range[0], g.y_range[0]]) / g.spacing, 0.0,
                    [g.ncol - 1, g.nrow - 1])
        c0 = np.minimum(f[..., 0].astype(int), g.ncol - 2)
        r0 = np.minimum(f[..., 1].astype(int), g.nrow - 2)
        u, v = f[..., 0] - c0, f[..., 1] - r0
        h00, h10, h01, h11 = h[r0, c0], h[r0, c0 + 1], h[r0 + 1, c0], h[r0 + 1, c0 + 1]
        lower = h00 + u * (h10 - h00) + v * (h11 - h10)  # triangle (0,0) (1,0) (1,1), where u >= v
        upper = h00 + v * (h01 - h00) + u * (h11 - h01)  # triangle (0,0) (0,1) (1,1)
        return np.where(u >= v, lower, upper)

    def max_height(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Upper bound (k,) of the surface over boxes [lo, hi] (k, 2): the highest vertex of the
        cells each box touches (the surface is linear on each cell triangle)."""
        g = self.grid
        origin, size = np.array([g.x_range[0], g.y_range[0]]), np.array([g.ncol, g.nrow])
        first = np.clip(np.floor((np.atleast_2d(lo) - origin) / g.spacing).astype(int), 0, size - 1)
        last = np.clip(np.ceil((np.atleast_2d(hi) - origin) / g.spacing).astype(int), 0, size - 1)
        return np.array([self.heights[a[1]:b[1] + 1, a[0]:b[0] + 1].max() for a, b in zip(first, last)])


@dataclass(frozen=True)
class Stairs:
    """`n_steps` steps up along +x from x = start, the last one a landing `landing` m long.

    With `down`, the mirror image: a landing `landing` m long ending at x = start at the top
    (n_steps * step_height), then steps down along +x to the floor.
    """

    step_height: float
    step_length: float = 0.3
    start: float = 1.0
    n_steps: int = 10
    width: float = 20.0  # along y, centred on y = 0
    landing: float = 6.0
    name: str = ""
    down: bool = False

    def __post_init__(self) -> None:
        _check("stair step height", self.step_height, 0.0, 0.3, "m")
        _check("stair step length", self.step_length, 0.1, 2.0, "m")
        _check("stair width", self.width, 0.5, 100.0, "m")
        _check("stair landing", self.landing, self.step_length, 100.0, "m")
        _check("stair start", self.start, -100.0, 100.0, "m")
        if not (isinstance(self.n_steps, (int, np.integer)) and 1 <= self.n_steps <= 100):
            raise ConfigError(f"number of stair steps must be an integer in [1, 100], got {self.n_steps}")
        if not isinstance(self.down, (bool, np.bool_)):
            raise ConfigError(f"stairs 'down' must be true or false, got {self.down!r}")
        if not self.name:
            way = ",down" if self.down else ""
            object.__setattr__(self, "name", f"stairs(h={self.step_height:g},l={self.step_length:g}{way})")

    @property
    def begin(self) -> float:
        """Where the stairs' ground starts along x (the floor is before it)."""
        return self.start - self.landing if self.down else -np.inf

    @property
    def end(self) -> float:
        """Where the stairs' ground ends along x (the floor is after it)."""
        return self.start + (self.n_steps - 1) * self.step_length + (0.0 if self.down else self.landing)

    def height(self, xy: np.ndarray) -> np.ndarray:
        def profile(x):
            steps = np.floor((x - self.start) / self.step_length) + 1.0
            if self.down:
                steps = self.n_steps - steps
            return self.step_height * np.clip(steps, 0.0, self.n_steps)

        return _along_x(self, xy, profile)

    def max_height(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        return _max_falling(self, lo, hi) if self.down else _max_rising(self, lo, hi)

    def boxes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(centre, half size) of each step: boxes from 0.1 m below the floor to the step's top."""
        out = []
        for k in range(1, self.n_steps + 1):
            if self.down:  # box 1 is the top landing, then the steps down
                x0 = self.start - self.landing if k == 1 else self.start + (k - 2) * self.step_length
                length = self.landing if k == 1 else self.step_length
                top = (self.n_steps - k + 1) * self.step_height
            else:
                x0 = self.start + (k - 1) * self.step_length
                length = self.landing if k == self.n_steps else self.step_length
                top = k * self.step_height
            out.append((np.array([x0 + length / 2, 0.0, (top - 0.1) / 2]),
                        np.array([length / 2, self.width / 2, (top + 0.1) / 2])))
        return out


@dataclass(frozen=True)
class Slope:
    """An incline up along +x at `angle_deg` from x = start for `length` m, then a level landing."""

    angle_deg: float
    start: float = 1.0
    length: float = 6.0
    width: float = 20.0
    landing: float = 6.0
    name: str = ""

    def __post_init__(self) -> None:
        _check("slope angle", self.angle_deg, 0.0, 30.0, "degrees")
        _check("slope length", self.length, 0.5, 100.0, "m")
        _check("slope width", self.width, 0.5, 100.0, "m")
        _check("slope landing", self.landing, 0.0, 100.0, "m")
        if not self.name:
            object.__setattr__(self, "name", f"slope({self.angle_deg:g}deg)")

    @property
    def rise(self) -> float:
        return self.length * np.tan(np.radians(self.angle_deg))

    @property
    def begin(self) -> float:
        return -np.inf

    @property
    def end(self) -> float:
        return self.start + self.length + self.landing

    def height(self, xy: np.ndarray) -> np.ndarray:
        slope = np.tan(np.radians(self.angle_deg))
        return _along_x(self, xy, lambda x: slope * np.clip(x - self.start, 0.0, self.length))

    def max_height(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        return _max_rising(self, lo, hi)

    def incline(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(centre, half size, quaternion) of the tilted box whose top face is the incline."""
        theta, half_thick = np.radians(self.angle_deg), 0.05
        top_centre = np.array([self.start + self.length / 2, 0.0, self.rise / 2])
        normal = np.array([-np.sin(theta), 0.0, np.cos(theta)])
        # Rotating by -theta about y turns the box's x axis up the slope.
        quat = np.array([np.cos(-theta / 2), 0.0, np.sin(-theta / 2), 0.0])
        half = np.array([self.length / (2 * np.cos(theta)), self.width / 2, half_thick])
        return top_centre - half_thick * normal, half, quat

    def top(self) -> tuple[np.ndarray, np.ndarray]:
        """(centre, half size) of the landing box, from 0.1 m below the floor to the top."""
        x0 = self.start + self.length
        length = max(self.landing, 1e-3)
        return (np.array([x0 + length / 2, 0.0, (self.rise - 0.1) / 2]),
                np.array([length / 2, self.width / 2, (self.rise + 0.1) / 2]))


Terrain = Flat | Rough | Stairs | Slope


def flat() -> Flat:
    return Flat()


def rough(grid: TerrainGrid, amplitude: float = 0.03, cell: float = 0.2, seed: int = 0) -> Rough:
    """Uniform random heights in [-amplitude, amplitude] on a lattice of `cell` metres, interpolated
    linearly onto `grid`; seeded, so the same arguments give the same terrain."""
    _check("rough terrain amplitude", amplitude, 0.0, 0.2, "m")
    _check("rough terrain cell", cell, grid.resolution, 5.0, "m")
    rng = np.random.default_rng(seed)
    lx = grid.x_range[0] + cell * np.arange(int(np.ceil(np.diff(grid.x_range)[0] / cell)) + 1)
    ly = grid.y_range[0] + cell * np.arange(int(np.ceil(np.diff(grid.y_range)[0] / cell)) + 1)
    lattice = rng.uniform(-amplitude, amplitude, size=(ly.size, lx.size))
    gy, gx = np.meshgrid(grid.y, grid.x, indexing="ij")
    # The lattice covers the grid; fill_value=None only absorbs rounding at its far edges.
    interpolate = RegularGridInterpolator((ly, lx), lattice, bounds_error=False, fill_value=None)
    heights = np.clip(interpolate(np.stack([gy, gx], axis=-1)), -amplitude, amplitude)
    return Rough(grid, heights, f"rough(a={amplitude:g},cell={cell:g},seed={seed})")


def _along_x(terrain: Stairs | Slope, xy: np.ndarray, profile) -> np.ndarray:
    """Height of a terrain whose `profile(x)` spans |y| <= width / 2 from x = begin (if it has one)
    up to x = end (floor elsewhere)."""
    xy = np.asarray(xy, dtype=float)
    x, y = xy[..., 0], xy[..., 1]
    inside = (x >= terrain.begin) & (x < terrain.end) & (np.abs(y) <= 0.5 * terrain.width)
    return np.where(inside, profile(x), 0.0)


def _max_rising(terrain: Stairs | Slope, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Highest point over boxes [lo, hi] (k, 2) of a terrain that never falls along x before its end
    (and is the floor after it): its height at the box's largest x short of the end."""
    lo, hi = np.atleast_2d(lo), np.atleast_2d(hi)
    x = np.minimum(hi[:, 0], np.nextafter(terrain.end, -np.inf))
    half = 0.5 * terrain.width
    touches = (lo[:, 0] < terrain.end) & (lo[:, 1] <= half) & (hi[:, 1] >= -half)
    return np.where(touches, terrain.height(np.stack([x, np.zeros_like(x)], -1)), 0.0)


def _max_falling(terrain: Stairs, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Highest point over boxes [lo, hi] (k, 2) of a terrain that never rises along x after its
    begin (and is the floor before it): its height at the box's smallest x from the begin on."""
    lo, hi = np.atleast_2d(lo), np.atleast_2d(hi)
    x = np.maximum(lo[:, 0], terrain.begin)
    half = 0.5 * terrain.width
    touches = (hi[:, 0] >= terrain.begin) & (lo[:, 1] <= half) & (hi[:, 1] >= -half)
    return np.where(touches, terrain.height(np.stack([x, np.zeros_like(x)], -1)), 0.0)


def _check(what: str, value: float, lo: float, hi: float, unit: str) -> None:
    if not (np.isfinite(value) and lo <= value <= hi):
        raise ConfigError(f"{what} must be in [{lo:g}, {hi:g}] {unit}, got {value}")
