"""Shared pieces of the environment and training tests: references recorded from the simulator
itself (so the physics can track them exactly) and environments built on them."""

from __future__ import annotations

import dataclasses
import fcntl
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from opt2skill.data.record import Trajectory
from opt2skill.envs import ReferenceBank, TrackingEnv, evaluation_config, tracking_config
from opt2skill.envs.config import TrackingConfig
from opt2skill.envs.recorded import record_reference, squat_targets
from opt2skill.model import load_robot

ROBOT = load_robot("digit")


def recorded_reference(steps: int = 60) -> tuple[Trajectory, np.ndarray]:
    """A squat recorded from the simulator (envs.recorded) and the PD targets that made it."""
    targets = squat_targets(ROBOT, steps)
    return record_reference(ROBOT, targets), targets


def exact_config(task: str = "recorded", **overrides) -> TrackingConfig:
    """No randomization, no noise, episodes from frame 0, penalties at full weight."""
    config = evaluation_config(tracking_config(task))
    return dataclasses.replace(config, **overrides)


def make_env(trajectories, config: TrackingConfig | None = None, num_envs: int = 1, seed: int = 0,
             dtype=np.float64, threads: int = 1) -> TrackingEnv:
    config = config or exact_config()
    bank = ReferenceBank.from_trajectories(ROBOT, trajectories, config.observations.end_effectors, dtype=dtype)
    return TrackingEnv(ROBOT, bank, config, num_envs, seed=seed, threads=threads)


def session_root(tmp_path_factory) -> Path:
    """A directory shared by this session's test workers and by no other session: under pytest-xdist
    each worker's base is <session>/popen-gwN; a plain run's base is the session directory itself
    (its parent would be shared with every earlier session, and stale artefacts would be reused)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def shared_dataset(tmp_path_factory, task: str, n: int, keep_gains: bool = False) -> Path:
    """A dataset made by `opt2skill generate TASK --n N [--keep-gains]`, once for all test workers (a
    file lock in the session's shared temporary directory; generation resumes, so a second call is a
    no-op)."""
    root = session_root(tmp_path_factory)
    name = f"{task}{n}" + ("g" if keep_gains else "")
    out = root / name
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        done = out / "trajectories"
        if not (done.is_dir() and len(list(done.glob("*.h5"))) >= n):
            cli = str(Path(sys.executable).parent / "opt2skill")
            gains = ["--keep-gains"] if keep_gains else []
            subprocess.run([cli, "generate", task, "--n", str(n), "--workers", "1", "--out", str(out), "--quiet", *gains],
                           check=True, capture_output=True, env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=600)
    return out
