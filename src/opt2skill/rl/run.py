"""A run directory: what the run is (config, dataset, robot), what produced it, and its outputs.

    RUN/run.json            identity (dataset and its identity, robot hash, task config, PPO config,
                            worlds, seed) and one entry per invocation (command, steps, provenance)
    RUN/checkpoints/        model_<iteration>.pt, the newest few (rl.checkpoint)
    RUN/tb/                 TensorBoard events (every reward term, episode figures, throughput)
    RUN/progress.jsonl      the same figures, one JSON line per iteration

Rerunning a command on an existing RUN resumes it if the identity is the same; any difference is an
error naming the differing keys, so a run never mixes two configurations. The one exception is the
dataset's path: a run and its dataset moved together (another machine, another checkout) resume
when the dataset's identity and size are the same, and run.json then records the new path and
the invocation where it moved from.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from opt2skill.data.atomic import dumps, write_json
from opt2skill.envs.config import EpisodeConfig, TrackingConfig
from opt2skill.errors import ConfigError, DataError
from opt2skill.folder_lock import LOCK_FILE
from opt2skill.rl.config import PPOConfig

FORMAT = "opt2skill-run"
FORMAT_VERSION = 1
RUN_FILE = "run.json"
PROGRESS_FILE = "progress.jsonl"


# Episode settings added after runs existed (adaptive starts); left out of run.json at their defaults,
# which reproduce the earlier behaviour, so those runs still resume.
LATER_EPISODE_KEYS = ("sampling", "bin_seconds", "lookback_seconds", "uniform_share", "half_life")


@dataclass(frozen=True)
class RunSpec:
    """Everything that decides what a run learns (not how long: steps can grow on a resume)."""

    dataset: str  # absolute path of the dataset directory
    dataset_identity: dict[str, Any]
    trajectories: int  # accepted trajectories used
    robot: str
    robot_hash: str
    tracking: TrackingConfig
    ppo: PPOConfig
    num_envs: int
    seed: int
    # The dataset's contacts, whose forces the policy observes (docs/envs.md); None: the robot's feet, as
    # every run before contacts beyond the feet (left out of run.json then, so those runs still resume).
    contacts: tuple[str, ...] | None = None
    # Processes training together (rl.processes), each with num_envs worlds: the batch of an iteration
    # is theirs together. 1 is left out of run.json (as every run before it, which still resume).
    processes: int = 1
    # The checkpoint PPO started from (`train --init-from`, a fine-tune of another run's policy): its
    # path, iteration and sha256 (a resume compares the content, not the path); None: a fresh actor
    # (left out of run.json then, as in every run before the option, which still resume).
    init_from: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        data = json.loads(dumps(dataclasses.asdict(self)))
        if data["contacts"] is None:
            del data["contacts"]
        if data["processes"] == 1:
            del data["processes"]
        if data["init_from"] is None:
            del data["init_from"]
        if not data["ppo"]["mixed_precision"]:  # float32, as every run before the option: left out, so they resume
            del data["ppo"]["mixed_precision"]
        noise = data["tracking"]["observations"]["noise"]
        if noise["per_world_min"] == 1.0:  # every world at full noise, as every run before the option
            del noise["per_world_min"]
        episodes, default = data["tracking"]["episodes"], dataclasses.asdict(EpisodeConfig())
        for key in LATER_EPISODE_KEYS:  # at their defaults they are what runs before them did: leave them out
            if episodes.get(key) == default[key]:
                del episodes[key]
        return data

    def contact_names(self, robot) -> tuple[str, ...]:
        """The contacts the run's policy observes forces at."""
        return self.contacts if self.contacts is not None else tuple(f.name for f in robot.config.feet)

    @staticmethod
    def contacts_of(robot, contact_names) -> tuple[str, ...] | None:
        """The `contacts` entry of a run on references with these contacts."""
        names = tuple(contact_names)
        return None if names == tuple(f.name for f in robot.config.feet) else names

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RunSpec:
        return config_from_dict(cls, data)


def config_from_dict(cls, data: dict[str, Any]):
    """A (nested, frozen) config dataclass from its `asdict` form read back from JSON."""
    if not isinstance(data, dict):
        raise DataError(f"expected a mapping for {cls.__name__}, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise DataError(f"unknown keys {unknown} in {cls.__name__}")
    kwargs = {}
    for name, value in data.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            value = config_from_dict(hint, value)
        elif isinstance(value, list):
            value = tuple(tuple(v) if isinstance(v, list) else v for v in value)
        kwargs[name] = value
    return cls(**kwargs)


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(d, dict):
        return {prefix: d}
    out = {}
    for k, v in d.items():
        out.update(_flatten(v, f"{prefix}{k}." if isinstance(v, dict) else f"{prefix}{k}"))
    return out


def differences(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    a, b = _flatten(old), _flatten(new)
    return [f"{k}: {a.get(k, '-')} -> {b.get(k, '-')}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]


def read_run(run: Path) -> dict[str, Any]:
    path = Path(run) / RUN_FILE
    if not path.is_file():
        raise DataError(f"{run} is not a training run (no {RUN_FILE})")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DataError(f"{path} is not valid JSON: {exc}") from None
    return check_format(path, data, FORMAT, FORMAT_VERSION, "run file")


def check_format(path: Path, data: Any, fmt: str, version: int, kind: str) -> dict[str, Any]:
    """`data` read from `path`, if it is a mapping of format `fmt` at `version`; else a DataError."""
    if not isinstance(data, dict) or data.get("format") != fmt:
        raise DataError(f"{path} is not an opt2skill {kind}")
    if data.get("format_version") != version:
        raise DataError(f"{path} has {kind} format version {data.get('format_version')}; this code reads {version}")
    return data


def read_spec(run: Path) -> RunSpec:
    return RunSpec.from_dict(read_run(run)["identity"])


def check_run(run: Path, spec: RunSpec) -> dict[str, Any] | None:
    """RUN's run file if RUN is a run of exactly `spec`, None if RUN is new (missing or empty); a
    ConfigError naming the differences otherwise. Reads only."""
    run = Path(run)
    if (run / RUN_FILE).is_file():
        data = read_run(run)
        moved = ("dataset: ", "init_from.checkpoint: ")  # paths: a run and its inputs may move together
        diff = [d for d in differences(data["identity"], spec.to_dict()) if not d.startswith(moved)]
        if diff:
            shown = "; ".join(diff[:6]) + (f"; and {len(diff) - 6} more" if len(diff) > 6 else "")
            raise ConfigError(f"{run} is a run with a different configuration ({shown}); choose another --out")
        return data
    if run.is_dir() and any(p.name != LOCK_FILE for p in run.iterdir()):
        raise ConfigError(f"--out {run} is a non-empty directory that is not a training run")
    return None


def open_run(run: Path, spec: RunSpec, invocation: dict[str, Any]) -> bool:
    """Create RUN for `spec`, or check that the existing RUN has exactly this spec. Records the
    invocation. Returns True if the run existed (a resume). Call with RUN's folder lock held."""
    run = Path(run)
    data = check_run(run, spec)
    entry = {"started": datetime.datetime.now().isoformat(timespec="seconds"), **invocation}
    if data is not None:
        if data["identity"]["dataset"] != spec.dataset:  # the same dataset (identity and size), moved
            entry["dataset_moved_from"] = data["identity"]["dataset"]
            data["identity"]["dataset"] = spec.dataset
        data["invocations"].append(entry)
        write_json(run / RUN_FILE, data)
        return True
    run.mkdir(parents=True, exist_ok=True)
    write_json(run / RUN_FILE, {"format": FORMAT, "format_version": FORMAT_VERSION, "identity": spec.to_dict(),
                                "invocations": [entry]})
    return False


def read_progress(run: Path) -> list[dict[str, Any]]:
    """The per-iteration figures logged so far (progress.jsonl)."""
    path = Path(run) / PROGRESS_FILE
    if not path.is_file():
        return []
    lines = [line for line in path.read_text().splitlines() if line.strip()]
    rows = [json.loads(line) for line in lines[:-1]]
    try:
        rows += [json.loads(line) for line in lines[-1:]]
    except ValueError:
        pass  # a last line cut short by a kill mid-write: its iteration is trained again
    return rows


def trim_progress(run: Path, last_iteration: int) -> None:
    """Drop lines logged after `last_iteration` (by a run killed after its last checkpoint)."""
    kept = [r for r in read_progress(run) if r["iteration"] <= last_iteration]
    path = Path(run) / PROGRESS_FILE
    if path.is_file():
        from opt2skill.data.atomic import atomic_path

        with atomic_path(path) as tmp:
            tmp.write_text("".join(dumps(r) + "\n" for r in kept))
