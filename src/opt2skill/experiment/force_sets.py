"""The wiping datasets of Table IV: one training set (force and desk height sampled in their
ranges), one held-out set per force level (the force pinned, `generate`'s range lo = hi; another
seed, so every level has the same desk heights and reaches), and the transfer test's reference (force
and desk height pinned). A set is named by what it holds, so two roles asking for the same references
(e.g. a level's set with the desk pinned, and the transfer's) share one dataset; its size is the
larger of theirs."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from opt2skill.experiment.sources import dataset_result
from opt2skill.experiment.table4_settings import TASK, Table4Settings

COMMAND = "opt2skill experiment table4"


@dataclass(frozen=True)
class WipeSet:
    force: tuple[float, float]  # N, sampled range (lo = hi: pinned)
    desk: tuple[float, float]  # m
    seed: int

    @property
    def name(self) -> str:
        return f"force{_span(self.force)}_desk{_span(self.desk)}_seed{self.seed}"


def _span(bounds: tuple[float, float]) -> str:
    lo, hi = bounds
    return f"{lo:g}" if lo == hi else f"{lo:g}-{hi:g}"


def roles(s: Table4Settings) -> dict[str, tuple[WipeSet, int]]:
    """Role ("train", "f<F>", "transfer") -> (its set, references it needs)."""
    out = {"train": (WipeSet(s.train_force, s.desk_height, s.seed), s.n_train)}
    for f in s.forces:
        out[level_key(f)] = (WipeSet((f, f), s.desk_height, s.seed + 1), s.n_test)
    if s.transfer_desks:
        pinned = WipeSet((s.transfer_force,) * 2, (s.transfer_height,) * 2, s.seed + 1)
        out["transfer"] = (pinned, s.n_transfer)
    return out


def level_key(force: float) -> str:
    return f"f{force:g}"


def datasets(s: Table4Settings) -> dict[str, tuple[WipeSet, int]]:
    """Set name -> (set, size): each distinct set once, as large as its largest role needs."""
    out: dict[str, tuple[WipeSet, int]] = {}
    for wipe_set, n in roles(s).values():
        known = out.get(wipe_set.name, (wipe_set, 0))[1]
        out[wipe_set.name] = (wipe_set, max(n, known))
    return out


def dataset_dir(out: Path, wipe_set: WipeSet) -> Path:
    return Path(out) / "data" / wipe_set.name


def build(wipe_set: WipeSet, n: int, s: Table4Settings, out: Path, progress: bool = True) -> dict[str, Any]:
    """Generate (or resume) one set; no accepted reference is `Unavailable`."""
    from opt2skill.trajopt.generate import GenerateRequest, generate

    folder = dataset_dir(out, wipe_set)
    summary = generate(GenerateRequest(task=TASK, n=n, seed=wipe_set.seed, out=folder, workers=s.workers,
                                       ranges={"force": wipe_set.force, "desk_height": wipe_set.desk},
                                       task_config=s.task_config(), command=COMMAND,
                                       keep_gains=s.distill_steps > 0 and wipe_set == roles(s)["train"][0]),
                       progress=progress)  # the expert to distil lives in the training set's gains
    return dataset_result(summary, folder, wipe_set.name)
