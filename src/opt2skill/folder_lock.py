"""One writer per output folder: an exclusive `flock` on FOLDER/.lock that names its holder.

Every command that writes a dataset, a run or an evaluation folder holds this lock while it writes.
A second writer gets one clear error naming the holder (pid, host, start time, command). The lock
is the OS's: it is released when the holding process dies, however it dies (kill -9 included),
so a lock file left by a killed process is stale by construction and the next writer takes it over;
the holder line it still contains is only reported. `flock` is not reliable on network file systems:
write runs and datasets to a local disk.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shlex
import socket
import sys
import warnings
from collections.abc import Iterator
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from opt2skill.errors import DataError, DataWarning

LOCK_FILE = ".lock"


def holder_info() -> dict[str, Any]:
    """What the lock file says about this process."""
    return {"pid": os.getpid(), "host": socket.gethostname(),
            "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "command": shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]])}


def read_holder(folder: str | Path) -> dict[str, Any] | None:
    """The holder recorded in FOLDER/.lock (the current one if the lock is held), None if unknown."""
    try:
        data = json.loads((Path(folder) / LOCK_FILE).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def describe(holder: dict[str, Any] | None) -> str:
    if not holder:
        return "a process that did not say who it is"
    return (f"pid {holder.get('pid')} on {holder.get('host')}, since {holder.get('started')}"
            + (f": {holder['command']}" if holder.get("command") else ""))


def _alive_here(holder: dict[str, Any]) -> bool:
    if holder.get("host") != socket.gethostname() or not isinstance(holder.get("pid"), int):
        return False
    try:
        os.kill(holder["pid"], 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextlib.contextmanager
def folder_lock(folder: str | Path, option: str = "--out") -> Iterator[None]:
    """Hold FOLDER's lock (creating FOLDER) while the block runs; a DataError naming the holder if
    another process holds it. Taking over from a killed writer is said with a DataWarning."""
    folder = Path(folder)
    created = not folder.exists()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        # Opened without truncating: the holder's line must survive a refused attempt.
        fd = os.open(folder / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:  # callers check their paths first (output_paths); this is the last word
        raise DataError(f"cannot write into {option} {folder} ({exc.strerror or exc})") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise DataError(f"another process is writing {folder} ({describe(read_holder(folder))}); "
                            f"wait for it to finish or choose another {option}") from None
        stale = read_holder(folder)
        if stale:
            state = "still running but no longer holds it" if _alive_here(stale) else "no longer running"
            warnings.warn(f"{folder} was left locked by {describe(stale)} ({state}); taking it over",
                          DataWarning, stacklevel=3)
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(holder_info()) + "\n").encode(), 0)
        try:
            yield
        finally:
            os.ftruncate(fd, 0)  # released: no holder to name
            if created:
                _remove_if_unused(folder)
    finally:
        os.close(fd)  # closing releases the flock (after the removal: no one can take it in between)


def _remove_if_unused(folder: Path) -> None:
    """A folder this lock made and nothing was written into (the command failed on its input)."""
    if [p.name for p in folder.iterdir()] == [LOCK_FILE]:
        with contextlib.suppress(OSError):  # a new writer came in between: it keeps the folder
            (folder / LOCK_FILE).unlink()
            folder.rmdir()
