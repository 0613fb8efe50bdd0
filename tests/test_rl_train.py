"""Training for real: PPO on squats made by `opt2skill generate` improves the tracking, and
`opt2skill train` resumes after a real kill, logs, checkpoints, plays back and refuses bad input."""

from __future__ import annotations

import dataclasses
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from envs_support import shared_dataset

from opt2skill.data.reader import Dataset
from opt2skill.envs import ReferenceBank, TrackingEnv, evaluation_config, tracking_config
from opt2skill.envs.evaluation import track
from opt2skill.model import load_robot
from opt2skill.errors import ConfigError, DataError
from opt2skill.rl import checkpoint, session
from opt2skill.rl.config import PPOConfig
from opt2skill.rl.run import read_progress, read_run
from opt2skill.rl.session import TrainRequest
from opt2skill.rl.trainer import Schedule, Trainer

CLI = [str(Path(sys.executable).parent / "opt2skill")]


@pytest.fixture(scope="module")
def squats(tmp_path_factory) -> Path:
    return shared_dataset(tmp_path_factory, "squat", 3)


def short_training_run(squats: Path, seed: int, iterations: int = 50, starts: int = 5) -> tuple[list, list]:
    """PPO with the default settings on three squats, terminations tight enough (5 cm of base height,
    0.3 rad of orientation) that the untrained policy (the default pose) loses most references; the
    deterministic policy tracked from fixed start frames (0, T/10, ..., 4T/10 of each squat, no
    noise) before and after `iterations` iterations of 32 worlds x 48 steps."""
    torch.manual_seed(seed)
    robot, dataset = load_robot("digit"), Dataset.open(squats)
    config = tracking_config("squat")
    config = dataclasses.replace(config, terminations=dataclasses.replace(
        config.terminations, max_height_error=0.05, max_orientation_error=0.3))
    bank = ReferenceBank.from_dataset(robot, dataset, config.observations.end_effectors, use_cache=False)
    trajectories = np.repeat(np.arange(bank.num_trajectories), starts)  # each from `starts` frames in its first half
    frames = (bank.length[trajectories] * np.tile(np.arange(starts), bank.num_trajectories)) // (2 * starts)
    with TrackingEnv(robot, bank, config, 32, seed=seed) as env, \
            TrackingEnv(robot, bank, evaluation_config(config), len(frames), seed=seed) as evaluation:
        trainer = Trainer(env, PPOConfig(), seed=seed)
        trainer.warm_up_normalizers()
        evaluation.set_progress(1.0)

        def policy(obs):
            with torch.no_grad():
                return trainer.alg.actor({"actor": torch.from_numpy(obs)}).numpy()

        before = track(evaluation, policy, trajectories, frames)
        trainer.train(Schedule(total_steps=iterations * trainer.batch), progress=False)
        after = track(evaluation, policy, trajectories, frames)
    return before, after


def test_a_short_training_run_raises_episode_reward_and_length(squats):
    """About a minute of real PPO (real MuJoCo, rsl_rl updates) measurably improves the tracking."""
    before, after = short_training_run(squats, seed=0)
    returns = [np.mean([m.reward for m in ms]) for ms in (before, after)]
    lengths = [np.mean([m.steps for m in ms]) for ms in (before, after)]
    assert np.mean([m.fell for m in before]) > 0.5  # the untrained policy loses most references
    assert lengths[1] > 1.1 * lengths[0], lengths
    assert returns[1] > 1.15 * returns[0], returns


def _train(squats: Path, out: Path, *extra: str, **kwargs) -> subprocess.CompletedProcess:
    args = [*CLI, "train", "--dataset", str(squats), "--out", str(out), "--num-envs", "4", "--quiet", *extra]
    return subprocess.run(args, capture_output=True, text=True, **kwargs)


def test_train_resumes_after_a_kill_and_play_rolls_the_checkpoint_out(squats, tmp_path):
    run = tmp_path / "run"
    steps = ["--steps", str(4 * 48 * 8), "--checkpoint-every", "1"]  # 8 iterations of 4 worlds x 48 steps
    args = [*CLI, "train", "--dataset", str(squats), "--out", str(run), "--num-envs", "4", "--quiet", *steps]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240
    while not (run / "checkpoints" / "model_00000003.pt").exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "no checkpoint in time"
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)  # a real kill: no chance to save anything
    proc.wait()
    killed_at = checkpoint.load(checkpoint.latest(run))["iteration"]
    assert 3 <= killed_at < 8
    done = _train(squats, run, *steps, timeout=600)
    assert done.returncode == 0, done.stderr
    final = checkpoint.load(checkpoint.latest(run))
    assert final["iteration"] == 8 and final["env_steps"] == 8 * 4 * 48
    # the optimizer went on from its saved state: Adam counted every update of every iteration
    assert int(final["alg"]["optimizer_state_dict"]["state"][0]["step"]) == 8 * 5 * 4
    progress = read_progress(run)
    assert [r["iteration"] for r in progress] == list(range(1, 9))  # nothing logged twice after the kill
    assert all(f"reward_terms/{t}" in progress[-1] for t in ("joint_pos", "contact_force", "joint_acc"))
    assert "terminations/unstable_worlds" in progress[-1] and progress[-1]["perf/env_steps_per_s"] > 0
    record = read_run(run)
    assert len(record["invocations"]) == 2
    assert record["identity"]["robot_hash"] == load_robot("digit").hash
    assert record["invocations"][0]["provenance"]["libraries"]["rsl-rl-lib"] == "5.5.1"
    assert list((run / "tb").glob("events.out.tfevents.*"))
    again = _train(squats, run, *steps, timeout=300)  # finished: says so, changes nothing
    assert again.returncode == 0 and "already trained" in again.stdout
    shown = subprocess.run([*CLI, "play", str(run), "--n", "2"], capture_output=True, text=True, timeout=300)
    assert shown.returncode == 0, shown.stderr
    for text in ("iteration 8", "joint_pos", "contact_force", "E_joint", "frames tracked"):
        assert text in shown.stdout, text


def test_bad_input_gets_one_clear_error_and_writes_nothing(squats, tmp_path):
    run = tmp_path / "run"
    foreign = tmp_path / "foreign"  # the same squats, made for another version of the robot file
    shutil.copytree(squats, foreign, ignore=shutil.ignore_patterns("cache", ".lock"))
    header = json.loads((foreign / "dataset.json").read_text())
    header["identity"]["robot_hash"] = "0" * 64
    (foreign / "dataset.json").write_text(json.dumps(header))
    cases = [
        (dict(dataset=tmp_path / "missing"), DataError, "missing"),
        (dict(history=99), ConfigError, r"--history must be in \[0, 50\]"),
        (dict(ablation="pos_x"), ConfigError, "--ablation must be one of pos, pos_f, pos_t, pos_f_t"),
        (dict(num_envs=0), ConfigError, r"--num-envs must be in \[1, 4096\]"),
        (dict(steps=0), ConfigError, "--steps must be a positive number"),
        (dict(dataset=foreign), DataError, "different 'digit' robot file"),
    ]
    for change, error, message in cases:
        request = dataclasses.replace(TrainRequest(dataset=squats, out=run, steps=192, num_envs=4), **change)
        with pytest.raises(error, match=message):
            session.train(request, progress=False)
        assert not run.exists()  # nothing written for bad input
    session.train(TrainRequest(dataset=squats, out=run, steps=192, num_envs=4), progress=False)
    with pytest.raises(ConfigError, match=r"different configuration \(.*tracking.observations.history: 10 -> 5"):
        session.train(TrainRequest(dataset=squats, out=run, steps=192, num_envs=4, history=5), progress=False)
    with pytest.raises(DataError, match="not a training run"):
        session.play(tmp_path)
    # the command line: one line on stderr, exit status 2, no traceback
    for args, message in ((["train", "--dataset", str(squats), "--out", str(tmp_path / "other"), "--ablation", "pos_x"],
                           "--ablation must be one of"), (["play", str(tmp_path)], "not a training run")):
        out = subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=120)
        lines = out.stderr.strip().splitlines()
        assert out.returncode == 2 and len(lines) == 1 and message in lines[0], out.stderr


def test_a_fine_tune_starts_from_another_runs_networks_optimizer_and_curriculum(squats, tmp_path):
    """`--init-from`: PPO goes on from a run's newest checkpoint under another reward (`--base-position`),
    recorded in the new run's identity; a checkpoint of other inputs or no checkpoint at all is refused
    before anything is written."""
    iteration = 4 * 48  # environment steps of one iteration: 4 worlds x 48 steps
    source, tuned = tmp_path / "source", tmp_path / "tuned"
    session.train(TrainRequest(dataset=squats, out=source, steps=2 * iteration, num_envs=4, threads=1), progress=False)
    start = checkpoint.load(checkpoint.latest(source))
    assert start["progress"] == pytest.approx(0.5)  # set before its second and last iteration
    request = TrainRequest(dataset=squats, out=tuned, steps=2 * iteration, num_envs=4, threads=1, init_from=source,
                           base_position="off")
    session.train(request, progress=False)
    identity = read_run(tuned)["identity"]
    assert identity["init_from"]["iteration"] == 2 and identity["init_from"]["checkpoint"].endswith("model_00000002.pt")
    assert identity["tracking"]["rewards"]["base_pos"]["weight"] == 0.0  # a squat's is 0.3: switched off
    assert read_run(source)["identity"]["tracking"]["rewards"]["base_pos"]["weight"] == 0.3
    # the curriculum goes on from the source's 0.5 toward the end over the fine-tune's own steps
    assert [r["curriculum/progress"] for r in read_progress(tuned)] == pytest.approx([0.5, 0.75])
    final = checkpoint.load(checkpoint.latest(tuned))
    assert final["iteration"] == 2 and final["curriculum_start"] == pytest.approx(0.5)
    # Adam went on counting from the source's updates (5 epochs x 4 minibatches per iteration)
    assert int(final["alg"]["optimizer_state_dict"]["state"][0]["step"]) == 4 * 5 * 4
    assert session.train(request, progress=False)["already_done"]  # a rerun resumes its own checkpoints
    for change, error, message in (
        (dict(history=5), DataError, "checkpoint of another policy: history 10 \\(expected 5\\)"),
        (dict(init_from=tmp_path / "empty"), DataError, "has no checkpoint to start from"),
        (dict(init_from=tmp_path / "missing.pt"), DataError, "does not exist"),
        (dict(base_position="maybe"), ConfigError, "--base-position must be one of task, on, off"),
        (dict(noise_min=1.5), ConfigError, "--noise-min must be a share in \\[0, 1\\]"),
    ):
        (tmp_path / "empty").mkdir(exist_ok=True)
        out = tmp_path / "refused"
        with pytest.raises(error, match=message):
            session.train(dataclasses.replace(request, out=out, **change), progress=False)
        assert not out.exists()
    out = subprocess.run([*CLI, "train", "--dataset", str(squats), "--out", str(tmp_path / "both"), "--init", "distill",
                          "--init-from", str(source)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "give one of them" in out.stderr and not (tmp_path / "both").exists()


def test_reward_terms_changed_from_table_i_train_are_recorded_and_bad_changes_refused(squats, tmp_path):
    """`--reward NAME=WEIGHT[:SCALE]`: the run trains with the changed terms (the logged term is paid at
    the new weight), run.json records them, a resume with other changes is refused; an unknown term,
    a wrong sign, a force or torque term without those inputs, or a malformed change is one error
    before anything is written."""
    from opt2skill.envs.config import parse_reward

    walk = tracking_config("walk", rewards_changed=(("base_lin_vel", 0.3, 8.0), ("base_pos", 0.2, None))).rewards
    assert (walk.base_lin_vel.weight, walk.base_lin_vel.scale) == (0.3, 8.0)
    assert (walk.base_pos.weight, walk.base_pos.scale) == (0.2, 20.0)  # on for walking, Table I's own kernel
    assert tracking_config("walk").rewards.base_pos.weight == 0.0 and tracking_config("walk").rewards.base_lin_vel.scale == 2.0
    assert parse_reward(" joint_pos = 0.5 : 3 ") == ("joint_pos", 0.5, 3.0) and parse_reward("torque=-0.1") == ("torque", -0.1, None)

    run = tmp_path / "run"
    request = TrainRequest(dataset=squats, out=run, steps=4 * 48, num_envs=4, threads=1,
                           rewards=(("base_ori", 0.0, None), ("joint_pos", 0.6, 2.5)))
    session.train(request, progress=False)
    rewards = read_run(run)["identity"]["tracking"]["rewards"]
    assert rewards["joint_pos"] == {"weight": 0.6, "scale": 2.5, "kernel": "exp_sq"} and rewards["base_ori"]["weight"] == 0.0
    logged = read_progress(run)[-1]
    assert logged["reward_terms/base_ori"] == 0.0 and 0.3 < logged["reward_terms/joint_pos"] <= 0.6
    with pytest.raises(ConfigError, match=r"different configuration \(.*joint_pos.scale: 2.5 -> 5.0"):
        session.train(dataclasses.replace(request, steps=2 * 4 * 48, rewards=(("base_ori", 0.0, None), ("joint_pos", 0.6, 5.0))),
                      progress=False)
    for rewards, message in (
        ((("speed", 1.0, None),), "unknown term 'speed'; terms: joint_pos, base_pos"),
        ((("joint_pos", -0.3, None),), "reward 'joint_pos' must have a weight >= 0"),
        ((("action_rate", 0.05, None),), "penalty 'action_rate' must have a weight <= 0"),
        ((("joint_pos", 0.3, -1.0),), "scale must be >= 0"),
        ((("joint_pos", float("inf"), None),), "weight and scale must be finite numbers, got inf"),
        ((("joint_pos", 0.3, float("nan")),), "weight and scale must be finite numbers, got 0.3 and nan"),
    ):
        out = tmp_path / "refused"
        with pytest.raises(ConfigError, match=message):
            session.train(dataclasses.replace(request, out=out, rewards=rewards), progress=False)
        assert not out.exists()
    with pytest.raises(ConfigError, match="no reference joint torques to reward"):
        TrainRequest(dataset=squats, out=tmp_path / "x", ablation="pos", rewards=(("joint_torque", 0.1, None),)).check()
    for text in ("joint_pos", "joint_pos=", "joint_pos=a:1", "=0.3"):
        out = subprocess.run([*CLI, "train", "--dataset", str(squats), "--out", str(tmp_path / "bad"), "--reward", text],
                             capture_output=True, text=True, timeout=120)
        lines = out.stderr.strip().splitlines()
        assert out.returncode == 2 and len(lines) == 1 and "--reward expects NAME=WEIGHT" in lines[0], (text, out.stderr)
        assert not (tmp_path / "bad").exists()
