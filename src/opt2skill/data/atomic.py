"""Crash-safe file writes: write under a temporary name, flush to disk, then rename.

A rename within one directory is atomic on POSIX file systems, so after a kill at any moment a path
holds either its complete old content or its complete new content, never a torn file. Leftover
temporaries (`*.tmp`) are the only trace of an interrupted write; `remove_temporaries` clears them.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

TMP_SUFFIX = ".tmp"


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yields a temporary path to write; on success it is synced and renamed to `path`."""
    path = Path(path)
    tmp = path.with_name(path.name + TMP_SUFFIX)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    finally:
        tmp.unlink(missing_ok=True)


def to_jsonable(obj: Any) -> Any:
    """numpy scalars and arrays as Python values; NaN and infinities as None (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if hasattr(obj, "tolist"):  # numpy scalar or array
        return to_jsonable(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps(obj: Any, indent: int | None = None) -> str:
    return json.dumps(to_jsonable(obj), indent=indent, allow_nan=False)


def write_json(path: str | Path, obj: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(dumps(obj, indent=2) + "\n")


def remove_temporaries(directory: str | Path) -> int:
    """Deletes interrupted writes below `directory`; returns how many there were."""
    removed = 0
    for tmp in Path(directory).rglob(f"*{TMP_SUFFIX}"):
        tmp.unlink(missing_ok=True)
        removed += 1
    return removed


def write_report_files(out_dir: str | Path, stem: str, obj: Any, markdown: str) -> tuple[Path, Path]:
    """OUT_DIR/STEM.json (the record) and OUT_DIR/STEM.md (tables to read), each written whole."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path, md_path = out_dir / f"{stem}.json", out_dir / f"{stem}.md"
    write_json(json_path, obj)
    with atomic_path(md_path) as tmp:
        tmp.write_text(markdown)
    return json_path, md_path
