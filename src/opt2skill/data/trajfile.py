"""One trajectory in one HDF5 file: a group with the record's arrays, JSON attributes and knots.

Layout of a file (docs/data.md):

    /traj_000123                 group, attributes: format, format_version, index, task, robot,
                                 seed, contact_names, ee_names, params, solver, validation,
                                 provenance, scene (JSON strings where not scalars; a file
                                 without `scene` predates scenes and reads as the flat floor),
                                 source, has_dynamics (a file without them predates kinematic
                                 records and reads as "to", True)
        time, qpos, ..., com     the frame fields, float64 (contact_active bool), gzip + shuffle,
                                 chunked along time
        knots/                   optional solver-grid arrays, dtype kept (feedback gains float32)
        prop_poses/NAME          optional, (T, 7) float64 reference pose of each moving prop of the
                                 scene (a box; a door's hinge frame) (x y z qw qx qy qz); a file
                                 without it reads as no poses

Files are written atomically (`opt2skill.data.atomic`). Anything that is not such a file (not
HDF5, truncated, another program's HDF5, a malformed attribute) raises a `DataError` that names
the file and the problem.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from opt2skill.data.atomic import atomic_path, dumps
from opt2skill.data.record import FRAME_FIELDS, Trajectory, checked_prop_poses
from opt2skill.errors import ConfigError, DataError
from opt2skill.scene.description import Scene

FORMAT = "opt2skill-trajectory"
FORMAT_VERSION = 1
CHUNK_FRAMES = 512
_JSON_ATTRS = ("contact_names", "ee_names", "params", "solver", "validation", "provenance")
_COMPRESSION = {"compression": "gzip", "compression_opts": 4, "shuffle": True}


def group_name(index: int) -> str:
    return f"traj_{int(index):06d}"


@dataclass(frozen=True)
class TrajectoryMeta:
    """A trajectory's attributes and length, read without its arrays."""

    path: Path
    group: str
    index: int
    task: str
    robot: str
    seed: int
    num_frames: int
    contact_names: tuple[str, ...]
    ee_names: tuple[str, ...]
    params: dict[str, float]
    solver: dict[str, Any]
    validation: dict[str, Any]
    provenance: dict[str, Any]
    knot_names: tuple[str, ...]
    scene: Scene
    source: str = "to"
    has_dynamics: bool = True


def write_trajectory(path: str | Path, traj: Trajectory, index: int, *, drop_knots: tuple[str, ...] = ()) -> None:
    """Write `traj` as the only group of a new file at `path`, atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            g = f.create_group(group_name(index))
            attrs = {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "index": int(index),
                "task": traj.task,
                "robot": traj.robot,
                "seed": int(traj.seed),
            }
            attrs.update({name: dumps(getattr(traj, name)) for name in _JSON_ATTRS})
            attrs["scene"] = dumps(traj.scene.to_dict())
            attrs["source"] = str(traj.source)
            attrs["has_dynamics"] = bool(traj.has_dynamics)
            g.attrs.update(attrs)
            for name in FRAME_FIELDS:
                _write_array(g, name, np.asarray(getattr(traj, name)))
            if traj.prop_poses:
                pg = g.create_group("prop_poses")
                for name, pose in traj.prop_poses.items():
                    _write_array(pg, name, np.asarray(pose, dtype=float))
            knots = {k: v for k, v in traj.knots.items() if k not in drop_knots}
            if knots:
                kg = g.create_group("knots")
                for name, value in knots.items():
                    _write_array(kg, name, np.asarray(value))


def _write_array(group: h5py.Group, name: str, value: np.ndarray) -> None:
    if value.ndim == 0 or value.size == 0:
        group.create_dataset(name, data=value)
        return
    chunks = (min(len(value), CHUNK_FRAMES), *value.shape[1:])
    group.create_dataset(name, data=value, chunks=chunks, **_COMPRESSION)


def open_file(path: str | Path) -> h5py.File:
    """Open for reading, with a clear error for a missing, truncated or non-HDF5 file."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"trajectory file not found: {path}")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        message = str(exc)  # h5py: "Unable to ... (the reason)"
        reason = message[message.find("(") + 1 : message.rfind(")")] if "(" in message else message
        raise DataError(f"{path} is not a readable HDF5 file ({reason}); it is truncated, corrupt or not HDF5") from None


def trajectory_groups(f: h5py.File) -> list[str]:
    """Names of the groups of `f` that hold an opt2skill trajectory (a foreign file has none)."""
    names = [name for name, obj in f.items() if isinstance(obj, h5py.Group) and obj.attrs.get("format") == FORMAT]
    if not names:
        raise DataError(
            f"{f.filename} is an HDF5 file but holds no opt2skill trajectory "
            f"(no group with attribute format='{FORMAT}')"
        )
    return sorted(names)


def _only_group(f: h5py.File, group: str | None) -> h5py.Group:
    names = trajectory_groups(f)
    if group is None:
        if len(names) != 1:
            raise DataError(f"{f.filename} holds {len(names)} trajectories; name one of {names}")
        group = names[0]
    if group not in names:
        raise DataError(f"{f.filename} has no trajectory group '{group}'; groups: {names}")
    g = f[group]
    version = g.attrs.get("format_version")
    if version != FORMAT_VERSION:
        raise DataError(f"{f.filename}:{group} has format version {version}; this version reads {FORMAT_VERSION}")
    return g


_ATTR_TYPES = {
    "index": int, "task": str, "robot": str, "seed": int, "contact_names": tuple, "ee_names": tuple,
    "params": dict, "solver": dict, "validation": dict, "provenance": dict,
}


def _attrs(g: h5py.Group) -> dict[str, Any]:
    """The group's attributes, decoded and typed (a DataError names any missing or malformed one)."""
    where = f"{g.file.filename}:{g.name}"
    out: dict[str, Any] = {}
    for name, kind in _ATTR_TYPES.items():
        if name not in g.attrs:
            raise DataError(f"{where} is missing attribute '{name}'")
        value = g.attrs[name]
        if isinstance(value, bytes):
            value = value.decode()
        if name in _JSON_ATTRS:
            try:
                value = json.loads(value)
            except (TypeError, ValueError) as exc:
                raise DataError(f"{where}: attribute '{name}' is not valid JSON ({exc})") from None
        expected = list if kind is tuple else kind
        if kind in (int, str):
            value = kind(value)
        elif not isinstance(value, expected):
            raise DataError(f"{where}: attribute '{name}' should be a JSON {expected.__name__}, got {value!r:.60}")
        out[name] = tuple(value) if kind is tuple else value
    return out


def _scene(g: h5py.Group) -> Scene:
    """The group's scene; files written before scenes existed were all made on the flat floor."""
    if "scene" not in g.attrs:
        return Scene()
    value = g.attrs["scene"]
    try:
        return Scene.from_dict(json.loads(value.decode() if isinstance(value, bytes) else value))
    except (TypeError, ValueError) as exc:
        raise DataError(f"{g.file.filename}:{g.name}: attribute 'scene' is not valid JSON ({exc})") from None
    except ConfigError as exc:
        raise DataError(f"{g.file.filename}:{g.name}: attribute 'scene' is not a valid scene: {exc}") from None


def _origin(g: h5py.Group) -> dict[str, Any]:
    """Source and has_dynamics; files written before kinematic records existed are TO records."""
    source = g.attrs.get("source", "to")
    source = source.decode() if isinstance(source, bytes) else str(source)
    return {"source": source, "has_dynamics": bool(g.attrs.get("has_dynamics", True))}


def _dataset(g: h5py.Group, name: str) -> h5py.Dataset:
    obj = g.get(name)
    if not isinstance(obj, h5py.Dataset):
        raise DataError(f"{g.file.filename}:{g.name} is missing the array '{name}'")
    return obj


def _read(ds: h5py.Dataset, sl: slice = slice(None)) -> np.ndarray:
    try:
        return ds[()] if ds.ndim == 0 or sl == slice(None) else ds[sl]
    except (OSError, ValueError) as exc:
        raise DataError(f"{ds.file.filename}:{ds.name} cannot be read ({exc}); the file is corrupt") from None


def _finite(ds: h5py.Dataset, value: np.ndarray) -> np.ndarray:
    """A frame field must hold numbers: NaN or infinity in a reference poisons every reader."""
    if value.dtype.kind == "f" and not np.isfinite(value).all():
        frame = int(np.argwhere(~np.isfinite(value))[0][0]) if value.ndim else 0
        raise DataError(f"{ds.file.filename}:{ds.name} holds NaN or infinity (first at row {frame})")
    return value


def _prop_poses(g: h5py.Group, frames: int, scene: Scene) -> dict[str, np.ndarray]:
    """The group's free-prop poses; files written before they existed have none."""
    pg = g.get("prop_poses")
    if not isinstance(pg, h5py.Group):
        return {}
    poses = {name: _finite(ds, _read(ds)) for name, ds in pg.items() if isinstance(ds, h5py.Dataset)}
    try:
        return checked_prop_poses(poses, frames, scene)
    except ValueError as exc:
        raise DataError(f"{g.file.filename}:{g.name}: {exc}") from None


def read_prop_poses(path: str | Path, group: str | None = None) -> dict[str, np.ndarray]:
    """Only the free props' reference poses (name -> (T, 7)) of a trajectory file."""
    with open_file(path) as f:
        g = _only_group(f, group)
        return _prop_poses(g, int(_dataset(g, "time").shape[0]), _scene(g))


def read_meta(path: str | Path, group: str | None = None) -> TrajectoryMeta:
    with open_file(path) as f:
        g = _only_group(f, group)
        knots = g.get("knots")
        return TrajectoryMeta(
            path=Path(path),
            group=g.name.lstrip("/"),
            num_frames=int(_dataset(g, "time").shape[0]),
            knot_names=tuple(knots.keys()) if isinstance(knots, h5py.Group) else (),
            scene=_scene(g),
            **_origin(g),
            **_attrs(g),
        )


def read_frames(
    path: str | Path, fields: tuple[str, ...], group: str | None = None, frames: slice = slice(None)
) -> dict[str, np.ndarray]:
    """Selected frame fields (and frame range) without reading the rest of the file."""
    unknown = [name for name in fields if name not in FRAME_FIELDS]
    if unknown:
        raise DataError(f"unknown frame fields {unknown}; fields: {', '.join(FRAME_FIELDS)}")
    with open_file(path) as f:
        g = _only_group(f, group)
        return {name: _finite(ds, _read(ds, frames)) for name in fields for ds in (_dataset(g, name),)}


def read_trajectory(path: str | Path, group: str | None = None, *, knots: bool = True) -> Trajectory:
    with open_file(path) as f:
        g = _only_group(f, group)
        a = _attrs(g)
        arrays = {name: _finite(ds, _read(ds)) for name in FRAME_FIELDS for ds in (_dataset(g, name),)}
        n = len(arrays["time"])
        bad = [name for name, value in arrays.items() if value.ndim == 0 or len(value) != n]
        if bad:
            raise DataError(f"{f.filename}:{g.name}: arrays {bad} do not have {n} frames like 'time'")
        knot_arrays = {}
        kg = g.get("knots")
        if knots and isinstance(kg, h5py.Group):
            knot_arrays = {name: _read(ds) for name, ds in kg.items() if isinstance(ds, h5py.Dataset)}
        a.pop("index")
        scene = _scene(g)
        return Trajectory(**arrays, **a, knots=knot_arrays, scene=scene, **_origin(g),
                          prop_poses=_prop_poses(g, n, scene))
