"""Training checkpoints: written atomically, found by iteration, the newest few kept.

A checkpoint holds everything a resumed run needs to go on as if it had not stopped: the actor and
critic (observation normalizers included), the optimizer state and adaptive learning rate, the
iteration and environment steps done, the curriculum position and the random number generators;
and its identity (robot file, task, ablation, history), checked wherever it is loaded.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import torch

from opt2skill.data.atomic import atomic_path, remove_temporaries
from opt2skill.errors import DataError
from opt2skill.rl.run import check_format

FORMAT = "opt2skill-checkpoint"
FORMAT_VERSION = 1
KEEP = 3  # newest checkpoints kept
_NAME = re.compile(r"^model_(\d{8})\.pt$")


DISTILL_STAGE_DIR = "distill"  # RUN/distill: the distillation stage of `train --init distill`


BEST_DIR = "best"  # RUN/best/model.pt: the best actor by held-out judgement (rl.best)


# RUN/final/model.pt: the actor of the finished run alone (about 3 MB against a checkpoint's 17), which
# an experiment keeps so that its policies can be evaluated again where its checkpoints are gone.
FINAL_DIR = "final"


def best_path(run: Path) -> Path:
    return Path(run) / BEST_DIR / "model.pt"


def final_path(run: Path) -> Path:
    return Path(run) / FINAL_DIR / "model.pt"


def policy_default(run: Path) -> Path | None:
    """The checkpoint that eval and export take when none is named: the best by held-out judgement if
    the run kept one (rl.best), else the newest, else the finished run's actor (`save_actor`)."""
    best, final = best_path(run), final_path(run)
    return best if best.is_file() else latest(run) or (final if final.is_file() else None)


def save_actor(source: Path, target: Path) -> Path:
    """`target`: the actor of checkpoint `source` (normalizer included) with its dims, identity and
    counts, without the critic, the optimizer and the generators; readable wherever a checkpoint is."""
    data = load(Path(source))
    actor = data["alg"]["actor_state_dict"] if "alg" in data else data["actor_state_dict"]
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(target) as tmp:
        torch.save({"format": FORMAT, "format_version": FORMAT_VERSION, "iteration": data["iteration"],
                    "env_steps": data["env_steps"], "elapsed": data.get("elapsed", 0.0), "dims": data["dims"],
                    "identity": data.get("identity"), "actor_state_dict": actor}, tmp)
    return target


def checkpoint_dir(run: Path) -> Path:
    return Path(run) / "checkpoints"


def policy_checkpoint_dirs(run: Path) -> tuple[Path, Path]:
    """Where a run's actors are: its PPO checkpoints, and its distillation stage's (if any)."""
    return checkpoint_dir(run), checkpoint_dir(Path(run) / DISTILL_STAGE_DIR)


def save(run: Path, iteration: int, payload: dict[str, Any]) -> Path:
    directory = checkpoint_dir(run)
    directory.mkdir(parents=True, exist_ok=True)
    remove_temporaries(directory)  # left by a writer killed mid-write (only the writer may remove them)
    path = directory / f"model_{iteration:08d}.pt"
    try:
        with atomic_path(path) as tmp:
            torch.save({"format": FORMAT, "format_version": FORMAT_VERSION, "iteration": iteration, **payload}, tmp)
    except (OSError, RuntimeError) as exc:  # a full disk, a quota (torch's writer raises RuntimeError): the
        kept = latest(run)  # temporary file is gone, the older checkpoints are untouched
        reason = getattr(exc, "strerror", None) or str(exc).splitlines()[0]
        raise DataError(f"cannot write checkpoint {path} ({reason}); "
                        + (f"the previous checkpoint {kept.name} is intact and a rerun resumes from it" if kept
                           else "no checkpoint was kept")) from None
    for old in list_checkpoints(run)[:-KEEP]:
        old.unlink(missing_ok=True)
    return path


def list_checkpoints(run: Path) -> list[Path]:
    """Checkpoint files of a run, oldest first (a write in progress or interrupted is not listed, and
    not removed: a reader must not delete a running trainer's temporary file)."""
    directory = checkpoint_dir(run)
    if not directory.is_dir():
        return []
    return sorted(p for p in directory.iterdir() if _NAME.match(p.name))


def latest(run: Path) -> Path | None:
    found = list_checkpoints(run)
    return found[-1] if found else None


def iteration_of(path: Path) -> int:
    """The iteration a checkpoint file holds, from its name (model_NNNNNNNN.pt), without loading it."""
    match = _NAME.match(Path(path).name)
    if match is None:
        raise ValueError(f"{path} is not named like a checkpoint (model_NNNNNNNN.pt)")
    return int(match.group(1))


def identity(robot: str, robot_hash: str, task: str, ablation: str, history: int, stride: int) -> dict[str, Any]:
    """What a checkpoint's networks are for: their inputs and outputs depend on all of it."""
    return {"robot": robot, "robot_hash": robot_hash, "task": task, "ablation": ablation, "history": history,
            "stride": stride}


def check_identity(path: Path, data: dict[str, Any], expected: dict[str, Any]) -> None:
    """DataError naming each difference between the checkpoint's identity and `expected` (checkpoints
    written before identities were recorded have none and pass)."""
    found = data.get("identity")
    if found is None:
        return
    diff = [f"{k} {found.get(k)!r} (expected {v!r})" for k, v in expected.items() if found.get(k) != v]
    if diff:
        raise DataError(f"{path} is a checkpoint of another policy: {'; '.join(diff)}")


def load(path: Path) -> dict[str, Any]:
    try:
        data = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # torch raises many kinds on a corrupt or foreign file
        raise DataError(f"{path} is not a readable checkpoint: {type(exc).__name__}: {str(exc).splitlines()[0]}") from None
    return check_format(path, data, FORMAT, FORMAT_VERSION, "checkpoint")
