"""Which files of a dataset folder are its trajectories, and whether each one is sound.

A trajectory file is named by its generation index, `NNNNNN.h5`; anything else in the folder (a
file manager's `000001 (copy).h5`, an editor's backup) is not part of the dataset and is skipped
with a warning. A trajectory file is sound when it is readable, the index stored in it equals its
name (a copy of trajectory 1 saved as 000042.h5 is not trajectory 42), and it was made for this
dataset (task, robot, seed, robot file). Bad files are reported together, with how to recover:
move them out of the way and let `generate` solve those indices again.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from opt2skill.data.atomic import TMP_SUFFIX
from opt2skill.data.trajfile import TrajectoryMeta, read_meta
from opt2skill.errors import DataError, DataWarning

QUARANTINE = "quarantine"
_NAME = {".h5": re.compile(r"^\d{6}\.h5$"), ".json": re.compile(r"^\d{6}\.json$")}
_IDENTITY_ATTRS = ("task", "robot", "seed")  # attributes every file repeats from the dataset's identity


def record_files(directory: Path, suffix: str) -> list[Path]:
    """The record files (`NNNNNN<suffix>`) of `directory`, by name; other files are skipped with a
    DataWarning (interrupted writes, `*.tmp`, silently: the next writer removes them)."""
    if not directory.is_dir():
        return []
    found, strays = [], []
    for path in sorted(directory.iterdir()):
        if _NAME[suffix].match(path.name):
            found.append(path)
        elif not path.name.endswith(TMP_SUFFIX):
            strays.append(path.name)
    if strays:
        warnings.warn(f"{directory}: skipped {len(strays)} file(s) not named like a trajectory record (NNNNNN{suffix}): "
                      f"{', '.join(strays[:5])}{', ...' if len(strays) > 5 else ''}", DataWarning, stacklevel=2)
    return found


def checked_meta(path: Path, identity: dict[str, Any]) -> TrajectoryMeta:
    """The file's attributes, if the file is sound for the dataset of `identity`; else a DataError
    saying what is wrong with it (without the recovery advice: see `BadFiles`)."""
    meta = read_meta(path)
    named = int(path.stem)
    if meta.index != named:
        raise DataError(f"{path} holds trajectory {meta.index}, not {named} (a copied or renamed file)")
    for key in _IDENTITY_ATTRS:
        if key in identity and getattr(meta, key) != identity[key]:
            raise DataError(f"{path} belongs to another dataset ({key} {getattr(meta, key)!r}, this dataset's "
                            f"{identity[key]!r})")
    stored_hash = meta.provenance.get("robot_hash")
    if stored_hash and identity.get("robot_hash") and stored_hash != identity["robot_hash"]:
        raise DataError(f"{path} was made with another robot file (hash {stored_hash[:12]}, this dataset's "
                        f"{identity['robot_hash'][:12]})")
    return meta


@dataclass
class BadFiles:
    """The unsound files of one dataset and the error that reports all of them at once."""

    root: Path
    header: dict[str, Any]
    problems: list[str]  # one DataError message per bad file

    def error(self) -> DataError:
        n = len(self.problems)
        files = "; ".join(self.problems)
        them = "it" if n == 1 else "them"
        return DataError(f"{n} bad trajectory file{'s' if n > 1 else ''} in {self.root}: {files}. To recover, move "
                         f"{them} to {self.root / QUARANTINE}/ (or delete {them}), then rerun {self._generate()} to "
                         "solve those indices again")

    def _generate(self) -> str:
        runs = self.header.get("runs") or [{}]
        command = runs[-1].get("command")
        return f"`{command}`" if command else "the `opt2skill generate` command that made the dataset"


def scan(paths: list[Path], identity: dict[str, Any]) -> tuple[dict[Path, TrajectoryMeta], list[str]]:
    """Every sound file's attributes, and a message per unsound one."""
    good, bad = {}, []
    for path in paths:
        try:
            good[path] = checked_meta(path, identity)
        except DataError as exc:
            bad.append(str(exc))
    return good, bad
