"""Output paths checked before the work: a command that would fail to write its result after a long
rollout or solve must fail in its first second instead, with one line saying why."""

from __future__ import annotations

import os
from pathlib import Path

from opt2skill.errors import ConfigError


def _creatable(path: Path, option: str, shown: Path) -> None:
    """`path` exists as a writable directory, or can be made: its nearest existing ancestor is a
    writable directory. `shown`: the path the user gave."""
    ancestor = path
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ConfigError(f"{option} {shown}: {ancestor} is a file, so no directory can be made there")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise ConfigError(f"{option} {shown}: {ancestor} is not writable")


def check_output_dir(path: str | Path, option: str = "--out") -> Path:
    """A directory a command will write into (made if missing)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{option} {path} is a file; give a directory")
    _creatable(path, option, path)
    return path


def check_output_file(path: str | Path, option: str = "--out", suffix: str | None = None) -> Path:
    """A file a command will write (its folder made if missing); `suffix` such as '.onnx' required."""
    path = Path(path)
    example = f"{path}/out{suffix or ''}"
    if path.is_dir():
        raise ConfigError(f"{option} {path} is a directory; give a file name such as {example}")
    if suffix and path.suffix != suffix:
        raise ConfigError(f"{option} must name a {suffix} file, got {path}")
    _creatable(path.parent, option, path)
    if path.exists() and not os.access(path, os.W_OK):
        raise ConfigError(f"{option} {path} exists and is not writable")
    return path
