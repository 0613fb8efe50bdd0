"""A scene as data: the terrain a motion is made on plus its props, checked, and JSON both ways.

`Scene` is what a trajectory record stores and what every consumer (optimizer, replay, environment,
render) builds from. Terrains are those of `scene.terrain` (flat, stairs, slope) plus `RoughGround`,
the seeded description of a rough heightfield. `to_dict` / `from_dict` are the JSON form:
`{"terrain": {"kind": "stairs", ...}, "props": [{"kind": "box", ...}, ...]}`; fields left out take
their defaults, anything unknown is a `ConfigError` naming what is allowed.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from opt2skill.errors import ConfigError
from opt2skill.scene.props import PROP_KINDS, Prop, Surface
from opt2skill.scene.terrain import Flat, Rough, Slope, Stairs, Terrain, TerrainGrid, rough


@dataclass(frozen=True)
class RoughGround:
    """Rough ground: `rough(grid, amplitude, cell, seed)` on a grid over `x_range` x `y_range`."""

    amplitude: float = 0.03
    cell: float = 0.2
    seed: int = 0
    x_range: tuple[float, float] = (-4.0, 16.0)
    y_range: tuple[float, float] = (-6.0, 6.0)
    resolution: float = 0.2

    def __post_init__(self) -> None:
        if not (isinstance(self.seed, (int, np.integer)) and not isinstance(self.seed, bool) and self.seed >= 0):
            raise ConfigError(f"rough ground seed must be a non-negative integer, got {self.seed!r}")
        self.terrain()  # the heightfield's own checks: amplitude, cell, grid

    def terrain(self) -> Rough:
        grid = TerrainGrid(x_range=self.x_range, y_range=self.y_range, resolution=self.resolution,
                           z_range=(-self.amplitude - 0.01, self.amplitude + 0.01))
        return rough(grid, self.amplitude, self.cell, seed=int(self.seed))


TERRAIN_KINDS: dict[str, type] = {"flat": Flat, "rough": RoughGround, "stairs": Stairs, "slope": Slope}
GroundSpec = Flat | RoughGround | Stairs | Slope


@dataclass(frozen=True)
class Scene:
    """Terrain plus props. The default is the flat floor with nothing on it."""

    terrain: GroundSpec = field(default_factory=Flat)
    props: tuple[Prop, ...] = ()

    def __post_init__(self) -> None:
        if isinstance(self.props, list):
            object.__setattr__(self, "props", tuple(self.props))
        self.check()

    def check(self) -> None:
        """A ConfigError naming the first thing that is not a known terrain, prop or unique name."""
        if not isinstance(self.terrain, tuple(TERRAIN_KINDS.values())):
            raise ConfigError(f"unknown terrain {self.terrain!r}; terrains: {', '.join(TERRAIN_KINDS)}")
        if not isinstance(self.props, tuple):
            raise ConfigError(f"scene props must be a list of props, got {self.props!r}")
        names = set()
        for prop in self.props:
            if not isinstance(prop, tuple(PROP_KINDS.values())):
                raise ConfigError(f"unknown prop {prop!r}; props: {', '.join(PROP_KINDS)}")
            if prop.name in names:
                raise ConfigError(f"two props are named '{prop.name}'; give each prop its own name")
            names.add(prop.name)

    @cached_property
    def ground(self) -> Terrain:
        """The terrain's geometry (for rough ground, its heightfield), built once."""
        return self.terrain.terrain() if isinstance(self.terrain, RoughGround) else self.terrain

    def ground_height(self, xy: np.ndarray) -> np.ndarray:
        """Terrain height (...,) under points xy (..., 2): the step tread, slope or heightfield
        surface the feet collide with in MuJoCo (props are not ground)."""
        return self.ground.height(np.asarray(xy, dtype=float))

    def prop(self, name: str) -> Prop:
        for prop in self.props:
            if prop.name == name:
                return prop
        raise ConfigError(f"the scene has no prop '{name}'; props: {[p.name for p in self.props]}")

    def with_prop(self, name: str, **changes: Any) -> Scene:
        """This scene with prop `name`'s fields replaced (e.g. a desk moved to another height, to
        test a policy in a scene its reference was not made in); the prop checks its new values."""
        prop = self.prop(name)
        fields = {f.name for f in dataclasses.fields(prop)} - {"name"}
        unknown = sorted(set(changes) - fields)
        if unknown:
            raise ConfigError(f"prop '{name}' ({_kind_of(prop)}) has no fields {unknown}; fields: {', '.join(sorted(fields))}")
        moved = dataclasses.replace(prop, **changes)
        return Scene(self.terrain, tuple(moved if p is prop else p for p in self.props))

    def surfaces(self) -> list[Surface]:
        return [s for prop in self.props for s in prop.surfaces()]

    def to_dict(self) -> dict[str, Any]:
        return {"terrain": _fields_of(self.terrain), "props": [_fields_of(p) for p in self.props]}

    @classmethod
    def from_dict(cls, raw: Any) -> Scene:
        if not isinstance(raw, dict):
            raise ConfigError(f"a scene must be a mapping with 'terrain' and 'props', got {raw!r:.60}")
        unknown = sorted(set(raw) - {"terrain", "props"})
        if unknown:
            raise ConfigError(f"unknown scene keys {unknown}; a scene has 'terrain' and 'props'")
        terrain = _build("terrain", TERRAIN_KINDS, raw.get("terrain", {"kind": "flat"}))
        props = raw.get("props", [])
        if not isinstance(props, list):
            raise ConfigError(f"scene props must be a list, got {props!r:.60}")
        return cls(terrain, tuple(_build("prop", PROP_KINDS, p) for p in props))


def _kind_of(obj) -> str:
    return next(kind for kind, cls in {**TERRAIN_KINDS, **PROP_KINDS}.items() if type(obj) is cls)


def _fields_of(obj) -> dict[str, Any]:
    """JSON fields of a terrain or prop: its kind and its dataclass fields (a terrain's display name,
    which its other fields determine, left out)."""
    out: dict[str, Any] = {"kind": _kind_of(obj)}
    for f in dataclasses.fields(obj):
        if f.name == "name" and not isinstance(obj, tuple(PROP_KINDS.values())):
            continue
        value = getattr(obj, f.name)
        out[f.name] = [_plain(v) for v in value] if isinstance(value, tuple) else _plain(value)
    return out


def _plain(value: Any) -> Any:
    """A numpy scalar as the Python number JSON can hold."""
    return value.item() if isinstance(value, np.generic) else value


def _build(what: str, kinds: dict[str, type], raw: Any):
    if not isinstance(raw, dict) or "kind" not in raw:
        raise ConfigError(f"a scene {what} must be a mapping with a 'kind' ({', '.join(kinds)}), got {raw!r:.60}")
    kind = raw["kind"]
    if kind not in kinds:
        raise ConfigError(f"unknown {what} kind {kind!r}; kinds: {', '.join(kinds)}")
    cls = kinds[kind]
    allowed = {f.name: f for f in dataclasses.fields(cls) if f.name != "name" or what == "prop"}
    unknown = sorted(set(raw) - set(allowed) - {"kind"})
    if unknown:
        raise ConfigError(f"scene {what} '{kind}': unknown fields {unknown}; fields: {', '.join(allowed)}")
    values = {}
    for name, value in raw.items():
        if name == "kind":
            continue
        default = allowed[name].default
        values[name] = _typed(f"scene {what} '{kind}' field '{name}'", value, default)
    missing = [f.name for f in allowed.values() if f.default is dataclasses.MISSING and f.name not in values]
    if missing:
        raise ConfigError(f"scene {what} '{kind}' needs the fields {missing}")
    return cls(**values)


def _typed(where: str, value: Any, default: Any) -> Any:
    """The JSON value as the field's type (taken from its default): lists become tuples of numbers."""
    if isinstance(default, tuple):
        if not isinstance(value, list) or not all(_is_number(v) for v in value):
            raise ConfigError(f"{where} must be a list of numbers, got {value!r:.60}")
        return tuple(float(v) for v in value)
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r:.60}")
        return value
    if isinstance(default, int):
        if not (_is_number(value) and float(value).is_integer()):
            raise ConfigError(f"{where} must be an integer, got {value!r:.60}")
        return int(value)
    if isinstance(default, float) or default is dataclasses.MISSING:  # required fields are numbers
        if not _is_number(value):
            raise ConfigError(f"{where} must be a number, got {value!r:.60}")
        return float(value)
    if isinstance(default, str) and not isinstance(value, str):
        raise ConfigError(f"{where} must be a string, got {value!r:.60}")
    return value


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)
