"""Which reference trajectories an evaluation uses, and whether the policy trained on them.

A trajectory is identified by its task and parameters (`fingerprint`): generation is deterministic
in them, so the same parameters in another dataset directory are the same motion. A policy's
training set is the list of fingerprints of the trajectories it trained on: a run trains on every
accepted trajectory its dataset had when it started (`RunSpec.trajectories` of them, in index
order), and an exported policy carries the list in its metadata. Splits:

- `held-out` (default): references the policy did not train on. From the run's own dataset these
  are the trajectories added after training started; usually they come from a second dataset
  (e.g. `opt2skill generate walk --seed 1 --out data/walk_test`).
- `training`: references it trained on (to measure the generalization gap).
- `all`: every reference, each marked as seen or not in the output.

This module is shared by `eval` and the standalone player, so it reads datasets only.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from opt2skill.data.reader import Dataset
from opt2skill.errors import ConfigError, DataError

SPLITS = ("held-out", "training", "all")
# End effectors and contacts the metrics of Tables III and IV compare.
HANDS = ("left_hand", "right_hand")
FEET = ("left_foot", "right_foot")


def fingerprint(task: str, params: dict[str, Any]) -> str:
    """A short stable id of a trajectory: its task and generation parameters."""
    text = json.dumps({"task": task, "params": params}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def dataset_fingerprints(dataset: Dataset, count: int | None = None) -> list[str]:
    """Fingerprints of the dataset's first `count` (default all) accepted trajectories (a DataError
    naming every bad file among them)."""
    count = len(dataset) if count is None else min(count, len(dataset))
    dataset.check(range(count))
    return [position_fingerprint(dataset, i) for i in range(count)]


def position_fingerprint(dataset: Dataset, position: int) -> str:
    meta = dataset.meta(position)
    return fingerprint(meta.task, meta.params)


@dataclass(frozen=True)
class ReferenceSet:
    """The references of one evaluation: dataset positions, generation indices, and the split."""

    dataset: str  # absolute path
    dataset_identity: dict[str, Any]
    positions: tuple[int, ...]  # positions in the dataset (its accepted trajectories, by index)
    indices: tuple[int, ...]  # generation indices (what users name with --index)
    split: str
    seen: tuple[bool | None, ...]  # the policy trained on it (None: unknown)
    note: str  # one line for the output: what was used and how it relates to training
    fingerprints: tuple[str, ...] = field(default=())

    def to_dict(self) -> dict[str, Any]:
        return {"dataset": self.dataset, "dataset_identity": self.dataset_identity, "split": self.split,
                "indices": list(self.indices), "seen_in_training": list(self.seen), "note": self.note,
                "fingerprints": list(self.fingerprints)}


def check_metric_fields(dataset: Dataset, task: str | None = None, position: int = 0,
                        contacts: Sequence[str] | None = None) -> None:
    """The references must carry what the metrics compare: both hands and feet as end effectors,
    and what the policy was trained on (checked on the trajectory at `position`: every file repeats
    the dataset's task, robot and contacts): its task and its `contacts` (the contacts whose forces it
    observes, in their order; None: not checked)."""
    if not len(dataset):
        raise DataError(f"dataset {dataset.root} has no accepted trajectories to evaluate on")
    meta = dataset.meta(position)
    if task and meta.task != task:
        raise DataError(f"dataset {dataset.root} holds '{meta.task}' trajectories; the policy was trained on '{task}'")
    missing = [name for name in (*HANDS, *FEET) if name not in meta.ee_names]
    if missing:
        raise DataError(f"dataset {dataset.root} lacks the end effectors {missing} that E_ee-hand/E_ee-foot compare "
                        f"(its records have {list(meta.ee_names)})")
    if contacts is not None:
        check_contacts(meta.contact_names, contacts, f"dataset {dataset.root}")


def check_contacts(found: Sequence[str], trained: Sequence[str], what: str) -> None:
    """One error naming both sets unless the references' contacts `found` are the policy's `trained`."""
    if tuple(found) != tuple(trained):
        raise DataError(f"{what} has contacts {list(found)}; the policy was trained on references with contacts "
                        f"{list(trained)} (its contact-force observations are sized and ordered by them)")


def select_references(dataset: Dataset, training: Collection[str] | None, n: int, split: str = "held-out",
                      indices: list[int] | None = None, what: str = "the policy") -> ReferenceSet:
    """Up to `n` references of `dataset` in the split (the first ones by generation index), or the
    given generation `indices`. `training`: fingerprints the policy trained on (None: unknown)."""
    if split not in SPLITS:
        raise ConfigError(f"--split must be one of {', '.join(SPLITS)}, got '{split}'")
    if n < 1:
        raise ConfigError(f"--n must be >= 1, got {n}")
    if not len(dataset):
        raise DataError(f"dataset {dataset.root} has no accepted trajectories to evaluate on")
    train = set(training) if training is not None else None

    def seen_in_training(prints: dict[int, str]) -> dict[int, bool | None]:
        return {p: None if train is None else f in train for p, f in prints.items()}

    if indices:  # only these files are read: a bad file elsewhere does not matter
        positions = [dataset.position(int(i)) for i in indices]
        prints = {p: position_fingerprint(dataset, p) for p in positions}
        seen = seen_in_training(prints)
    else:
        prints = dict(enumerate(dataset_fingerprints(dataset)))
        seen = seen_in_training(prints)
        if train is None and split != "all":
            raise DataError(f"cannot tell which references {what} trained on (its training dataset is gone or "
                            "changed); pass --split all to evaluate on every reference anyway")
        wanted = {"held-out": False, "training": True}.get(split)
        positions = [p for p in range(len(dataset)) if wanted is None or seen[p] == wanted][:n]
        if not positions:
            hint = ("generate a separate test dataset (e.g. opt2skill generate walk --seed 1 --out data/walk_test) "
                    "and pass it with --dataset, or use --split training") if split == "held-out" else "use --split all"
            raise DataError(f"dataset {dataset.root} has no {split} references for {what}: {hint}")
    chosen_seen = tuple(seen[p] for p in positions)
    known = [s for s in chosen_seen if s is not None]
    if not known:
        relation = "unknown whether the policy trained on them"
    elif not any(known):
        relation = "none used in training (held out)"
    elif all(known):
        relation = "all used in training (NOT held out)"
    else:
        relation = f"{sum(known)} of {len(known)} used in training"
    idx = tuple(int(dataset.indices[p]) for p in positions)
    note = f"{len(positions)} reference{'s' if len(positions) > 1 else ''} of {Path(dataset.root).resolve()} (indices {_ranges(idx)}): {relation}"
    return ReferenceSet(dataset=str(Path(dataset.root).resolve()), dataset_identity=dataset.identity,
                        positions=tuple(positions), indices=idx, split="given" if indices else split,
                        seen=chosen_seen, note=note, fingerprints=tuple(prints[p] for p in positions))


def _ranges(values: tuple[int, ...]) -> str:
    """'0-3, 7, 9-10' for (0, 1, 2, 3, 7, 9, 10)."""
    parts, start = [], None
    for i, v in enumerate(values):
        if start is None:
            start = v
        if i + 1 == len(values) or values[i + 1] != v + 1:
            parts.append(f"{start}" if start == v else f"{start}-{v}")
            start = None
    return ", ".join(parts)
