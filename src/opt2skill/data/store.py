"""A dataset directory: one HDF5 file per trajectory, failure records, a header and a summary.

    DIR/dataset.json              header: what the dataset is (task, robot, seed, parameter ranges,
                                  validation limits, ...) and the runs that wrote it
    DIR/trajectories/000123.h5    accepted trajectories (opt2skill.data.trajfile)
    DIR/rejected/000007.h5        trajectories that failed validation, kept with their figures
    DIR/failed/000012.json        solves that produced nothing (solver error, worker crash,
                                  timeout): index, parameters, kind, message
    DIR/summary.json              counts, reasons, timings, parameter coverage (derived)
    DIR/.lock                     held (flock) by the one process writing the directory

Every file is written atomically and named by the trajectory's index, so the files present are the
exact record of what is finished: a killed run loses only the trajectories in flight, and rerunning
the same command skips every index already recorded.
"""

from __future__ import annotations

import contextlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from opt2skill.data.atomic import remove_temporaries, write_json
from opt2skill.data.file_check import BadFiles, record_files, scan
from opt2skill.data.record import Trajectory
from opt2skill.data.trajfile import TrajectoryMeta, write_trajectory
from opt2skill.errors import DataError
from opt2skill.folder_lock import LOCK_FILE, folder_lock

DATASET_FORMAT = "opt2skill-dataset"
DATASET_FORMAT_VERSION = 1
HEADER = "dataset.json"
SUMMARY = "summary.json"
ACCEPTED, REJECTED, FAILED = "accepted", "rejected", "failed"
_DIRS = {ACCEPTED: "trajectories", REJECTED: "rejected", FAILED: "failed"}
_RANK = {ACCEPTED: 0, REJECTED: 1, FAILED: 2}  # which record wins if a retry was interrupted


@dataclass
class Outcome:
    """What happened to one trajectory index."""

    index: int
    status: str  # accepted | rejected | failed
    params: dict[str, float]
    reasons: list[str] = field(default_factory=list)  # failed checks, or the failure kind
    message: str = ""
    solve_time: float | None = None  # s, wall time of the whole solve (solver["total_time"])
    validation_time: float | None = None
    iterations: int | None = None
    figures: dict[str, Any] = field(default_factory=dict)
    limits: dict[str, Any] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)

    @classmethod
    def from_meta(cls, meta: TrajectoryMeta, status: str) -> Outcome:
        v = meta.validation
        return cls(
            index=meta.index,
            status=status,
            params=meta.params,
            reasons=list(v.get("reasons", [])),
            solve_time=meta.solver.get("total_time", meta.solver.get("solve_time")),
            validation_time=v.get("time"),
            iterations=meta.solver.get("iterations"),
            figures=dict(v.get("figures", {})),
            limits=dict(v.get("limits", {})),
            units=dict(v.get("units", {})),
        )


def file_name(index: int, suffix: str) -> str:
    return f"{int(index):06d}{suffix}"


def read_json(path: Path, what: str) -> dict[str, Any]:
    try:
        obj = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"{what} not found: {path}") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise DataError(f"{path} is not valid JSON ({exc}); the {what} is corrupt") from None
    if not isinstance(obj, dict):
        raise DataError(f"{path}: the {what} must be a JSON object")
    return obj


def read_header(root: Path) -> dict[str, Any]:
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"dataset directory not found: {root}")
    path = root / HEADER
    if not path.is_file():
        raise DataError(f"{root} is not an opt2skill dataset (no {HEADER})")
    header = read_json(path, "dataset header")
    if header.get("format") != DATASET_FORMAT:
        raise DataError(f"{path} is not an opt2skill dataset header (format is {header.get('format')!r})")
    if header.get("format_version") != DATASET_FORMAT_VERSION:
        raise DataError(
            f"{path} has format version {header.get('format_version')}; this version reads {DATASET_FORMAT_VERSION}"
        )
    if not isinstance(header.get("identity"), dict):
        raise DataError(f"{path} has no 'identity' object")
    return header


def _mismatches(stored: dict[str, Any], wanted: dict[str, Any], prefix: str = "") -> list[str]:
    out = []
    for key in sorted(set(stored) | set(wanted)):
        a, b = stored.get(key), wanted.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _mismatches(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key}: dataset has {json.dumps(a)}, this command {json.dumps(b)}")
    return out


class DatasetStore:
    """Writes and lists the outcomes of one dataset directory (see the module docstring)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def path(self, status: str, index: int) -> Path:
        return self.root / _DIRS[status] / file_name(index, ".json" if status == FAILED else ".h5")

    def lock(self) -> contextlib.AbstractContextManager[None]:
        """Exclusive write access (opt2skill.folder_lock); released by the OS if the process dies."""
        return folder_lock(self.root)

    def prepare(self, identity: dict[str, Any], run: dict[str, Any]) -> tuple[dict[str, Any], dict[int, Outcome]]:
        """Create the header, or check that an existing dataset has the same identity; log the run.

        Returns the header and the outcomes already recorded.

        Call with the lock held. A different task, robot, seed, parameter range or validation
        limit is an error naming each difference; so are bad record files (all of them at once).
        Nothing is written before these checks pass.
        """
        identity = json.loads(json.dumps(identity))  # the form it takes on disk
        header_path = self.root / HEADER
        if header_path.exists():
            header = read_header(self.root)
            diffs = _mismatches(header["identity"], identity)
            if diffs:
                raise DataError(
                    f"{self.root} holds a different dataset ({'; '.join(diffs)}); use the same settings to "
                    "resume it, or another --out"
                )
        elif any(p.name != LOCK_FILE for p in self.root.iterdir()):
            raise DataError(f"{self.root} is not empty and not an opt2skill dataset; choose another --out")
        else:
            header = {"format": DATASET_FORMAT, "format_version": DATASET_FORMAT_VERSION, "identity": identity, "runs": []}
        outcomes = self.outcomes(header)
        header["runs"] = [*header.get("runs", []), run]
        write_json(header_path, header)  # first, so that a directory with our subfolders is always ours
        for sub in _DIRS.values():
            (self.root / sub).mkdir(exist_ok=True)
        remove_temporaries(self.root)
        for outcome in outcomes.values():  # a retry killed between its write and the old record's removal
            self._remove_others(outcome)
        return header, outcomes

    def _scan(self, identity: dict[str, Any]) -> tuple[list[Outcome], list[str]]:
        found, bad = [], []
        for status, sub in _DIRS.items():
            directory = self.root / sub
            if status == FAILED:
                for path in record_files(directory, ".json"):
                    try:
                        found.append(self._read_failure(path))
                    except DataError as exc:
                        bad.append(str(exc))
            else:
                metas, problems = scan(record_files(directory, ".h5"), identity)
                found += [Outcome.from_meta(meta, status) for meta in metas.values()]
                bad += problems
        return found, bad

    def outcomes(self, header: dict[str, Any]) -> dict[int, Outcome]:
        """Every recorded index with its outcome (accepted over rejected over failed if both exist);
        a DataError listing every bad record file of the dataset of `header`."""
        found, bad = self._scan(header["identity"])
        if bad:
            raise BadFiles(self.root, header, bad).error()
        best: dict[int, Outcome] = {}
        for outcome in found:
            previous = best.get(outcome.index)
            if previous is None or _RANK[outcome.status] < _RANK[previous.status]:
                best[outcome.index] = outcome
        return dict(sorted(best.items()))

    def _read_failure(self, path: Path) -> Outcome:
        raw = read_json(path, "failure record")
        try:
            outcome = Outcome(**{k: raw[k] for k in Outcome.__dataclass_fields__ if k in raw})
        except TypeError as exc:
            raise DataError(f"{path} is not a failure record ({exc})") from None
        if outcome.index != int(path.stem):
            raise DataError(f"{path} records index {outcome.index}, not {int(path.stem)} (a copied or renamed file)")
        return outcome

    def write_trajectory(self, outcome: Outcome, traj: Trajectory, drop_knots: tuple[str, ...] = ()) -> Path:
        path = self.path(outcome.status, outcome.index)
        write_trajectory(path, traj, outcome.index, drop_knots=drop_knots)
        self._remove_others(outcome)
        return path

    def write_failure(self, outcome: Outcome) -> Path:
        path = self.path(FAILED, outcome.index)
        write_json(path, asdict(outcome))
        self._remove_others(outcome)
        return path

    def _remove_others(self, outcome: Outcome) -> None:
        for status in _DIRS:
            if status != outcome.status:
                self.path(status, outcome.index).unlink(missing_ok=True)

    def write_summary(self, summary: dict[str, Any]) -> None:
        write_json(self.root / SUMMARY, summary)

    def files(self, status: str = ACCEPTED) -> list[Path]:
        """The trajectory files of `status`, by index (other files skipped with a warning)."""
        return record_files(self.root / _DIRS[status], ".h5")
