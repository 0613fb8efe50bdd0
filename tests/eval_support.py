"""Shared pieces of the evaluation and deployment tests: a real (briefly) trained run, shared by
every test worker, and small datasets written from records in memory."""

from __future__ import annotations

import dataclasses
import fcntl
import subprocess
import sys
from pathlib import Path

import numpy as np

from envs_support import ROBOT, session_root, shared_dataset

from opt2skill.data.record import Trajectory
from opt2skill.data.store import ACCEPTED, DatasetStore, Outcome

CLI = str(Path(sys.executable).parent / "opt2skill")
ITERATIONS = 2  # PPO iterations of the shared run: a real policy, trained for seconds


def shared_run(tmp_path_factory) -> tuple[Path, Path]:
    """(run, dataset): `opt2skill train` for two iterations of 4 worlds on three generated squats,
    made once for all test workers (a file lock; training resumes, so a second call is a no-op)."""
    dataset = shared_dataset(tmp_path_factory, "squat", 3)
    root = session_root(tmp_path_factory)
    run = root / "eval_run"
    with open(root / "eval_run.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (run / "checkpoints" / f"model_{ITERATIONS:08d}.pt").exists():
            steps = 4 * 48 * ITERATIONS  # 4 worlds x 48 steps (0.24 s) per iteration
            subprocess.run([CLI, "train", "--dataset", str(dataset), "--out", str(run), "--num-envs", "4", "--steps",
                            str(steps), "--checkpoint-every", "1", "--threads", "1", "--quiet"],
                           check=True, capture_output=True, timeout=600)
    return run, dataset


def gliding(traj: Trajectory, distance: float) -> Trajectory:
    """`traj` with its whole body carried `distance` m along +x over the motion: a reference that
    travels (for the terrain sweep's machinery), whatever the motion itself is."""
    shift = np.linspace(0.0, distance, traj.num_frames)
    qpos, ee_pos, com = traj.qpos.copy(), traj.ee_pos.copy(), traj.com.copy()
    qpos[:, 0] += shift
    ee_pos[..., 0] += shift[:, None]
    com[:, 0] += shift
    return dataclasses.replace(traj, qpos=qpos, ee_pos=ee_pos, com=com)


def write_dataset(root: Path, trajectories: list[Trajectory], task: str | None = None) -> Path:
    """A dataset directory holding `trajectories` as accepted, indices 0..n-1."""
    store = DatasetStore(root)
    identity = {"task": task or trajectories[0].task, "robot": ROBOT.name, "robot_hash": ROBOT.hash, "seed": 0}
    with store.lock():
        store.prepare(identity, {"command": "test"})
        for i, traj in enumerate(trajectories):
            if task:
                traj = dataclasses.replace(traj, task=task)
            store.write_trajectory(Outcome(i, ACCEPTED, traj.params), traj)
    return root
