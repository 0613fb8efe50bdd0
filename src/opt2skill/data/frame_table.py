"""The in-memory frame table of a dataset, and its on-disk cache.

A `FrameTable` holds chosen fields of many trajectories stacked along rows, with index maps
(trajectory, frame) <-> row. Building one decompresses every trajectory file (about a minute for
2000 walks of 14 s); the cache keeps the table as uncompressed `.npy` arrays in
`DIR/cache/frames_<key>/` and maps them read-only next time. The key covers the fields, the dtype
and each file's name, size and modification time, so any change to the dataset makes a new entry.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class FrameTable:
    """Frames of several trajectories stacked along rows, one array per field.

    Rows `start[t] : start[t] + length[t]` hold trajectory `t` of the table (position `t` in
    `trajectories`, the dataset positions it was built from).
    """

    fields: dict[str, np.ndarray]
    trajectories: np.ndarray  # (n,) dataset positions of the table's trajectories
    start: np.ndarray  # (n,) first row of each
    length: np.ndarray  # (n,) frames of each

    def __getitem__(self, field: str) -> np.ndarray:
        return self.fields[field]

    @property
    def num_rows(self) -> int:
        return int(self.length.sum())

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.fields.values())

    def row(self, traj: np.ndarray | int, frame: np.ndarray | int) -> np.ndarray:
        """Row of `frame` of table trajectory `traj` (arrays broadcast). Out of range is an error."""
        traj, frame = np.asarray(traj), np.asarray(frame)
        if np.any(traj < 0) or np.any(traj >= len(self.start)):
            raise IndexError(f"trajectory index out of range [0, {len(self.start)})")
        if np.any(frame < 0) or np.any(frame >= self.length[traj]):
            raise IndexError("frame index beyond the trajectory's length")
        return self.start[traj] + frame

    def locate(self, row: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """(table trajectory, frame) of each row."""
        row = np.asarray(row)
        if np.any(row < 0) or np.any(row >= self.num_rows):
            raise IndexError(f"row out of range [0, {self.num_rows})")
        traj = np.searchsorted(self.start, row, side="right") - 1
        return traj, row - self.start[traj]


def key(fields: Sequence[str], dtype, files: Sequence[Path]) -> str:
    stamp = [list(fields), None if dtype is None else np.dtype(dtype).str]
    for path in files:
        st = path.stat()
        stamp.append([path.name, st.st_size, st.st_mtime_ns])
    return hashlib.sha256(json.dumps(stamp).encode()).hexdigest()[:16]


def load(directory: Path, trajectories: np.ndarray) -> FrameTable | None:
    """The cached table at `directory` (arrays mapped read-only), or None if there is none."""
    index = directory / "index.npz"
    if not index.is_file():
        return None
    with np.load(index) as idx:
        start, length, names = idx["start"], idx["length"], [str(n) for n in idx["fields"]]
    fields = {name: np.load(directory / f"{name}.npy", mmap_mode="r") for name in names}
    return FrameTable(fields=fields, trajectories=np.asarray(trajectories), start=start, length=length)


def save(table: FrameTable, directory: Path) -> None:
    """Write the cache entry atomically (a directory renamed into place); skipped if not writable."""
    partial = directory.with_name(directory.name + ".partial")
    try:
        shutil.rmtree(partial, ignore_errors=True)
        partial.mkdir(parents=True)
        for name, array in table.fields.items():
            np.save(partial / f"{name}.npy", array)
        np.savez(partial / "index.npz", start=table.start, length=table.length, fields=np.array(list(table.fields)))
        os.replace(partial, directory)
    except OSError:  # a read-only dataset, a full disk: the table is still returned
        shutil.rmtree(partial, ignore_errors=True)
