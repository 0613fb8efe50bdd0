"""The training loop on small real cases: a diverged world is reset, counted in the logs and does not
stop training; TensorBoard gets every reward term, the episode figures and the throughput; training
is a function of its seed; a checkpoint of another policy is refused wherever it is loaded."""

from __future__ import annotations

import dataclasses
import os
import signal

import numpy as np
import pytest
import torch
from envs_support import exact_config, make_env, recorded_reference
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from torch.utils.tensorboard import SummaryWriter

from opt2skill.envs import tracking_config
from opt2skill.envs.config import RewardConfig
from opt2skill.errors import DataError
from opt2skill.rl import checkpoint, processes
from opt2skill.rl.config import PPOConfig
from opt2skill.rl.policy import load_policy
from opt2skill.rl.run import RunSpec, open_run, read_progress
from opt2skill.rl.trainer import Schedule, Trainer

SMALL = PPOConfig(rollout_seconds=0.1, hidden_dims=(32, 32))  # 20 steps per world and iteration


@pytest.fixture(scope="module")
def reference():
    return recorded_reference(steps=30)[0]


def test_a_diverged_world_is_counted_in_the_logs_and_training_goes_on(reference, tmp_path):
    env = make_env([reference], num_envs=4)
    trainer = Trainer(env, SMALL, tmp_path, seed=0)
    trainer.warm_up_normalizers()
    qpos, qvel = env.state.qpos.copy(), env.state.qvel.copy()
    qvel[1, 6:] = 1e6  # world 1 explodes at the first step of the first rollout
    env.sim.reset(np.array([1]), qpos[1:2], qvel[1:2], targets=qpos[1:2, 7:])
    writer = SummaryWriter(str(tmp_path / "tb"))
    figures = trainer.train(Schedule(total_steps=2 * trainer.batch), progress=False, writer=writer)
    writer.close()
    first, second = read_progress(tmp_path)
    assert first["terminations/unstable_worlds"] == 1 and first["terminations/unstable"] == 1
    assert second["terminations/unstable_worlds"] == 0
    assert trainer.iteration == 2 and all(np.isfinite(v) for v in figures.values())
    assert all(torch.isfinite(p).all() for p in trainer.alg.actor.parameters())
    scalars = EventAccumulator(str(tmp_path / "tb")).Reload().Tags()["scalars"]
    expected = [f"reward_terms/{name}" for name in RewardConfig().terms()] + [
        "reward/step", "episode/length_s", "episode/reward", "terminations/unstable_worlds",
        "perf/env_steps_per_s", "perf/learner_samples_per_s", "curriculum/noise_factor", "loss/value"]
    assert not [tag for tag in expected if tag not in scalars]


def test_training_is_a_function_of_its_seed(reference):
    config = tracking_config("recorded")  # Table II randomization and observation noise on

    def parameters_after_training(seed: int) -> torch.Tensor:
        with make_env([reference], config, num_envs=4, seed=seed) as env:
            trainer = Trainer(env, SMALL, None, seed=seed)
            trainer.warm_up_normalizers()
            for _ in range(2):
                trainer.train_iteration()
            return torch.cat([p.detach().flatten() for p in trainer.alg.actor.parameters()])

    first = parameters_after_training(0)
    assert torch.equal(first, parameters_after_training(0))
    assert not torch.equal(first, parameters_after_training(1))


def test_a_checkpoint_of_another_policy_is_refused(reference, tmp_path):
    with make_env([reference], num_envs=2) as env:
        Trainer(env, SMALL, tmp_path / "a", seed=0).save()
    saved = checkpoint.latest(tmp_path / "a")
    config = exact_config()
    shorter = dataclasses.replace(config, observations=dataclasses.replace(config.observations, history=5))
    with make_env([reference], shorter, num_envs=2) as env:  # resuming with another history length
        trainer = Trainer(env, SMALL, tmp_path / "a", seed=0)
        with pytest.raises(DataError, match=r"checkpoint of another policy: history 10 \(expected 5\)"):
            trainer.resume_latest()
    spec = RunSpec(dataset="/d", dataset_identity={}, trajectories=1, robot="digit", robot_hash=env.robot.hash,
                   tracking=tracking_config("recorded", "pos"), ppo=SMALL, num_envs=2, seed=0)
    open_run(tmp_path / "b", spec, {})
    with pytest.raises(DataError, match=r"ablation 'pos_f_t' \(expected 'pos'\)"):
        load_policy(tmp_path / "b", saved)  # e.g. eval or export given a checkpoint of run a


def test_the_learner_sits_on_the_physics_gpu_and_on_the_cpu_otherwise(reference):
    """PPO learns where the physics is for one process on a GPU (rsl_rl's networks, storage and the
    observations handed to it), on the CPU for C MuJoCo and Warp's CPU device, and on the CPU for a
    group of processes (gloo averages their gradients). A policy snapshot always acts on the CPU."""
    from opt2skill.rl.policy import Policy
    from opt2skill.sim.devices import learner_device

    assert learner_device("cuda") == "cuda" and learner_device("cuda:1") == "cuda:1"
    assert learner_device("cpu") == learner_device("warp-cpu") == learner_device("cuda:1", processes=2) == "cpu"
    env = make_env([reference], num_envs=2)
    trainer = Trainer(env, SMALL, None, seed=0)
    obs = trainer.venv.get_observations()
    assert trainer.venv.device == torch.device("cpu") and obs.device == trainer.venv.device
    assert {p.device for p in trainer.alg.actor.parameters()} == {trainer.venv.device}
    actions = Policy(trainer.alg.actor)(obs["actor"].numpy())
    assert isinstance(actions, np.ndarray) and actions.shape == (2, env.nu)


def test_a_sigterm_during_the_update_ends_training_after_it_with_the_iteration_saved(reference, tmp_path,
                                                                                       monkeypatch):
    """SIGTERM lands inside the second PPO update: the update, its counters and its log line finish,
    then training stops and checkpoints the two whole iterations (before, the half-updated networks
    were not saved and the run fell back to its last periodic checkpoint)."""
    env = make_env([reference], num_envs=2)
    trainer = Trainer(env, SMALL, tmp_path, seed=0)
    trainer.warm_up_normalizers()
    update, updates = trainer.alg.update, []

    def update_with_a_signal_inside():
        updates.append(1)
        if len(updates) == 2:
            os.kill(os.getpid(), signal.SIGTERM)
        return update()

    monkeypatch.setattr(trainer.alg, "update", update_with_a_signal_inside)
    previous = signal.getsignal(signal.SIGTERM)
    processes.terminate_as_interrupt()
    try:
        with pytest.raises(KeyboardInterrupt):
            trainer.train(Schedule(total_steps=5 * trainer.batch, checkpoint_every=100), progress=False)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert trainer.iteration == 2 and len(updates) == 2 and len(read_progress(tmp_path)) == 2
    saved = checkpoint.load(checkpoint.latest(tmp_path))
    assert saved["iteration"] == 2 and saved["env_steps"] == 2 * trainer.batch
    restored = Trainer(make_env([reference], num_envs=2), SMALL, tmp_path, seed=0)
    restored.restore(saved)
    for a, b in zip(restored.alg.actor.parameters(), trainer.alg.actor.parameters()):
        assert torch.equal(a, b)
