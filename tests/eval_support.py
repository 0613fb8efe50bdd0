"""Shared pieces of the evaluation and deployment tests: a real (briefly) trained run, shared by
every test worker, and small datasets written from records in memory."""

from __future__ import annotations

import dataclasses
import fcntl
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np

from envs_support import ROBOT, session_root, shared_dataset

from opt2skill.data.record import Trajectory
from opt2skill.data.store import ACCEPTED, DatasetStore, Outcome
from opt2skill.deploy.observations import ReferenceFrames
from opt2skill.deploy.player import Player
from opt2skill.envs import ReferenceBank, TrackingEnv, evaluation_config
from opt2skill.envs.config import TerminationConfig
from opt2skill.eval.evaluate import load_run_policy

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


def player_matches_environment(run: Path, onnx: Path, reference: Trajectory) -> float:
    """The largest relative difference between the player's observation and the training
    environment's over a rollout of `reference`. The environment steps with the policy's actions plus
    noise (so the histories hold distinct values); at every step the player reads its sensors at the
    environment's state, keeps its own histories and builds the observation from the metadata."""
    source = load_run_policy(run)
    config = dataclasses.replace(evaluation_config(source.spec.tracking), terminations=TerminationConfig(
        max_height_error=0, max_orientation_error=0, max_xy_error=0, min_height=0))
    bank = ReferenceBank.from_trajectories(source.robot, [reference], config.observations.end_effectors, dtype=np.float64)
    player = Player(onnx)
    frames = ReferenceFrames(reference, player.contacts)
    rng = np.random.default_rng(0)
    action, worst = None, 0.0
    with TrackingEnv(source.robot, bank, config, 1, seed=0, threads=1) as env:
        env.reset_worlds(np.array([0]), np.array([0]), np.array([0]))
        for t in range(reference.num_frames - 1):
            expected, _ = env.observations()
            state = env.state
            player.data.qpos[:], player.data.qvel[:] = state.qpos[0], state.qvel[0]
            mujoco.mj_forward(player.model, player.data)
            readings = player.sense()
            if action is None:
                player.observation.reset(readings.joint_pos, (reference.qpos[0, 7:] - player.default_pose) / player.scale)
            else:
                player.observation.push(readings.joint_pos, action)
            got = player.observation.observe(readings, frames, t)
            worst = max(worst, float(np.abs(got - expected[0]).max() / (1 + np.abs(expected[0]).max())))
            action = np.clip(source.policy(expected)[0] + 0.3 * rng.standard_normal(source.robot.nu), -10, 10)
            assert not env.step(action[None]).episodes or t == reference.num_frames - 2
    return worst
