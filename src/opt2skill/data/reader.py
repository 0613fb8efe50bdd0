"""Reading datasets: random access to trajectories, and an in-memory frame table for training.

    ds = Dataset.open("data/walk")            # the accepted trajectories, ordered by index
    len(ds); ds[i] -> Trajectory; ds.meta(i); ds.frames(i, ("qpos",), 100, 200)
    table = ds.frame_table(("qpos", "qvel", "joint_torque"), dtype=np.float32)
    row = table.row(traj, frame); traj, frame = table.locate(rows)

The RL environment samples a trajectory and a start frame per episode and then reads frames one
after another: `frame_table` loads the chosen fields of every (or a chosen subset of) trajectory
into one contiguous array per field, so that is an index computation, not file access.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from opt2skill.data import frame_table as cache
from opt2skill.data.file_check import BadFiles, scan
from opt2skill.data.frame_table import FrameTable
from opt2skill.data.record import FRAME_FIELDS, Trajectory
from opt2skill.data.store import ACCEPTED, SUMMARY, DatasetStore, read_header, read_json
from opt2skill.data.trajfile import TrajectoryMeta, read_frames, read_prop_poses, read_trajectory
from opt2skill.errors import DataError


class Dataset:
    """The trajectories of one dataset directory with one status (accepted by default)."""

    def __init__(self, root: Path, header: dict[str, Any], files: list[Path]):
        self.root = root
        self.header = header
        self.files = files
        self.indices = np.array([int(p.stem) for p in files], dtype=np.int64)
        self._meta: dict[int, TrajectoryMeta] = {}

    @classmethod
    def open(cls, root: str | Path, status: str = ACCEPTED) -> Dataset:
        root = Path(root)
        header = read_header(root)
        return cls(root, header, DatasetStore(root).files(status))

    @property
    def identity(self) -> dict[str, Any]:
        return self.header["identity"]

    def summary(self) -> dict[str, Any] | None:
        path = self.root / SUMMARY
        return read_json(path, "dataset summary") if path.exists() else None

    def __len__(self) -> int:
        return len(self.files)

    def _path(self, i: int) -> Path:
        if not -len(self) <= i < len(self):
            raise IndexError(f"trajectory {i} out of range: the dataset {self.root} has {len(self)}")
        return self.files[i]

    def _bad(self, problems: list[str]) -> DataError:
        return BadFiles(self.root, self.header, problems).error()

    def __getitem__(self, i: int) -> Trajectory:
        self.meta(i)  # the file is sound (its name, its dataset)
        try:
            return read_trajectory(self._path(i))
        except DataError as exc:  # unreadable arrays, NaN or infinity
            raise self._bad([str(exc)]) from None

    def __iter__(self) -> Iterator[Trajectory]:
        return (self[i] for i in range(len(self)))

    def position(self, index: int) -> int:
        """Dataset position of the trajectory generated with `index`."""
        hits = np.flatnonzero(self.indices == index)
        if not len(hits):
            raise DataError(f"{self.root} has no trajectory with index {index}")
        return int(hits[0])

    def meta(self, i: int) -> TrajectoryMeta:
        """Trajectory i's attributes; a DataError with the recovery advice if its file is bad."""
        i = i % len(self) if len(self) else i
        if i not in self._meta:
            self.check([i])
        return self._meta[i]

    def check(self, positions: Sequence[int] | None = None) -> None:
        """Check the files of `positions` (all by default): one DataError naming every bad one."""
        wanted = range(len(self)) if positions is None else [int(p) for p in positions]
        paths = {}
        for p in wanted:
            path = self._path(p)  # IndexError when out of range
            paths[p % len(self)] = path
        todo = {p: path for p, path in paths.items() if p not in self._meta}
        good, bad = scan(list(todo.values()), self.identity)
        if bad:
            raise self._bad(bad)
        self._meta.update({p: good[path] for p, path in todo.items()})

    def sound(self, positions: Sequence[int]) -> list[int]:
        """Those of `positions` whose files are sound (the others are skipped)."""
        kept = []
        for p in positions:
            try:
                self.meta(int(p))
            except DataError:
                continue
            kept.append(int(p))
        return kept

    def frames(self, i: int, fields: Sequence[str], start: int = 0, stop: int | None = None) -> dict[str, np.ndarray]:
        """Some fields of some frames of one trajectory, read from disk."""
        fields = tuple(fields)
        unknown = [f for f in fields if f not in FRAME_FIELDS]
        if unknown:
            raise DataError(f"unknown frame fields {unknown}; fields: {', '.join(FRAME_FIELDS)}")
        self.meta(i)
        try:
            return read_frames(self._path(i), fields, frames=slice(start, stop))
        except DataError as exc:
            raise self._bad([str(exc)]) from None

    def prop_poses(self, i: int) -> dict[str, np.ndarray]:
        """Trajectory i's free-prop reference poses (name -> (T, 7)); empty when it has none."""
        self.meta(i)
        try:
            return read_prop_poses(self._path(i))
        except DataError as exc:
            raise self._bad([str(exc)]) from None

    def frame_table(
        self,
        fields: Sequence[str] = FRAME_FIELDS,
        dtype: np.dtype | type | None = None,
        subset: Sequence[int] | None = None,
        progress: bool = False,
        use_cache: bool = False,
    ) -> FrameTable:
        """Load `fields` of the trajectories `subset` (all by default) into memory.

        `dtype` converts floating-point fields (e.g. np.float32 halves the memory); `contact_active`
        stays bool. `use_cache`: keep the table as uncompressed arrays under DIR/cache and map them
        read-only next time (seconds instead of a minute for 2000 walks; processes share the pages).
        """
        fields = tuple(fields)
        unknown = [f for f in fields if f not in FRAME_FIELDS]
        if unknown:
            raise DataError(f"unknown frame fields {unknown}; fields: {', '.join(FRAME_FIELDS)}")
        positions = np.arange(len(self)) if subset is None else np.asarray(subset, dtype=np.int64)
        if len(positions) == 0:
            raise DataError(f"no trajectories to load from {self.root}")
        self.check(positions)  # every bad file named at once, before any loading
        if use_cache:
            files = [self._path(int(p)) for p in positions]
            where = self.root / "cache" / f"frames_{cache.key(fields, dtype, files)}"
            table = cache.load(where, positions)
            if table is None:
                table = self.frame_table(fields, dtype, positions, progress)
                cache.save(table, where)
            return table
        length = np.array([self.meta(int(p)).num_frames for p in positions], dtype=np.int64)
        start = np.concatenate([[0], np.cumsum(length)[:-1]])
        first = read_frames(self._path(int(positions[0])), fields, frames=slice(0, 1))
        arrays = {}
        for name, sample in first.items():
            kind = sample.dtype if (dtype is None or sample.dtype == bool) else np.dtype(dtype)
            arrays[name] = np.empty((int(length.sum()), *sample.shape[1:]), dtype=kind)
        iterator = enumerate(positions)
        if progress:
            from tqdm import tqdm

            iterator = tqdm(iterator, total=len(positions), desc="loading frames", unit="traj")
        for t, p in iterator:
            try:
                chunk = read_frames(self._path(int(p)), fields)
            except DataError as exc:  # unreadable arrays, NaN or infinity
                raise self._bad([str(exc)]) from None
            rows = slice(start[t], start[t] + length[t])
            for name, value in chunk.items():
                if value.shape[1:] != arrays[name].shape[1:] or len(value) != length[t]:
                    raise DataError(f"{self._path(int(p))}: '{name}' has shape {value.shape}, unlike the other trajectories")
                arrays[name][rows] = value
        return FrameTable(fields=arrays, trajectories=positions, start=start, length=length)
