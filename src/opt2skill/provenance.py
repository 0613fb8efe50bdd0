"""What produced an output: versions, robot file hash, code version. Recorded in every output."""

from __future__ import annotations

import functools
import importlib.metadata as md
import platform
import subprocess
from pathlib import Path
from typing import Any

import opt2skill

_PACKAGES = ("crocoddyl", "pin", "mujoco", "numpy", "torch", "rsl-rl-lib", "h5py", "onnx", "onnxruntime")


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """opt2skill's version, plus the git commit (and '+dirty') when run from a checkout."""
    root = Path(opt2skill.__file__).resolve().parents[2]
    try:
        commit = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=5,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit, dirty = "", ""
    version = opt2skill.__version__
    return f"{version}+{commit}{'.dirty' if dirty else ''}" if commit else version


@functools.lru_cache(maxsize=1)
def library_versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for package in _PACKAGES:
        try:
            versions[package] = md.version(package)
        except md.PackageNotFoundError:
            continue
    return versions


def provenance(robot_hash: str, **extra: Any) -> dict[str, Any]:
    return {
        "code_version": code_version(),
        "robot_hash": robot_hash,
        "libraries": library_versions(),
        "machine": platform.machine(),
        **extra,
    }
