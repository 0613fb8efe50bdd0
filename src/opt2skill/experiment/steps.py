"""Steps of an experiment, each marked done on disk (OUT/steps/NAME.json) when it finishes.

A rerun skips every marked step; an unmarked one runs again, and the commands it wraps resume
their own work (generation by index, training from its newest checkpoint). A step that cannot run
for want of input (a source without usable references) is marked `unavailable` with the reason, so
the report can say so and a rerun does not try again.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from opt2skill.cli.console import console
from opt2skill.data.atomic import write_json

DONE, UNAVAILABLE = "done", "unavailable"


class Unavailable(Exception):
    """A step cannot run with what the experiment has (the reason is recorded, the experiment goes on)."""


class Steps:
    def __init__(self, out: Path, total: int):
        self.folder = Path(out) / "steps"
        self.total = total
        self.count = 0
        self.timings: dict[str, float] = {}

    def marker(self, name: str) -> Path:
        return self.folder / f"{name}.json"

    def record(self, name: str) -> dict[str, Any] | None:
        path = self.marker(name)
        return json.loads(path.read_text()) if path.is_file() else None

    def amend(self, name: str, result: dict[str, Any]) -> None:
        """Replace finished step `name`'s result (what it recorded, with more added)."""
        entry = self.record(name)
        if entry is None:
            raise KeyError(name)
        write_json(self.marker(name), {**entry, "result": result})

    def run(self, name: str, what: str, work: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        """Run `work` unless step `name` is marked; its result (JSON-able) is the marker's `result`."""
        self.count += 1
        head = f"[{self.count}/{self.total}] {what}"
        known = self.record(name)
        if known is not None:
            console.print(f"{head}: {known['status']} before ({known['elapsed_s']:.0f} s), skipped", highlight=False)
            return known
        console.rule(f"[bold]{head}")
        start = time.perf_counter()
        try:
            result, status = work(), DONE
        except Unavailable as exc:
            result, status = {"reason": str(exc)}, UNAVAILABLE
            console.print(f"[yellow]{what}: unavailable: {exc}[/]", highlight=False, soft_wrap=True)
        elapsed = time.perf_counter() - start
        self.timings[name] = elapsed
        entry = {"step": name, "what": what, "status": status, "elapsed_s": elapsed, "result": result,
                 "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        self.folder.mkdir(parents=True, exist_ok=True)
        write_json(self.marker(name), entry)
        return entry
