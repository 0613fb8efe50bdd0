"""Distillation in a short real run: real squats with their DDP gains, real MuJoCo worlds, real Adam
steps on the PPO actor. The loss falls and the distilled actor tracks a training reference where an
untrained actor does not."""

import copy
import dataclasses
import os
import signal

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from opt2skill.envs import ReferenceBank, TrackingEnv, evaluation_config, tracking_config
from opt2skill.envs.evaluation import track
from opt2skill.errors import ConfigError
from opt2skill.eval.metrics import tracking_errors
from opt2skill.expert.acting import EnvExpert
from opt2skill.model import load_robot
from opt2skill.rl import checkpoint, processes
from opt2skill.rl.anchor import ExpertAnchor
from opt2skill.rl.distill import Distiller, LabelBuffer
from opt2skill.rl.distill_config import DistillConfig, distillation_tracking_config, finetune_tracking_config
from opt2skill.rl.policy import Policy, build_actor
from opt2skill.rl.trainer import Trainer
from opt2skill.tasks import get_task

ROBOT = load_robot("digit")
SMALL = DistillConfig(updates_per_iteration=8, batch_size=512, buffer_samples=20_000)


@pytest.fixture(scope="module")
def squats():
    task = get_task("squat", ROBOT, {"solver.keep_gains": True})
    return [task.solve(task.param_space().check({"depth": depth}), seed=0) for depth in (0.15, 0.1)]


def tracked_joint_error(actor, reference) -> tuple[float, bool]:
    config = evaluation_config(tracking_config("squat"))
    bank = ReferenceBank.from_trajectories(ROBOT, [reference], config.observations.end_effectors)
    with TrackingEnv(ROBOT, bank, config, 1, seed=0, threads=1) as env:
        env.set_progress(1.0)
        motion = track(env, Policy(copy.deepcopy(actor)), np.arange(1))[0]
    return tracking_errors(reference, motion.record(ROBOT, reference), fell=motion.fell).E_joint, motion.fell


def bc_loss(actor, obs: torch.Tensor, label: torch.Tensor) -> float:
    with torch.no_grad():
        return float(torch.mean((actor(TensorDict({"actor": obs}, batch_size=[len(obs)])) - label) ** 2))


def test_distillation_loss_falls_and_the_actor_tracks_better_than_untrained(squats):
    torch.manual_seed(0)
    config = distillation_tracking_config(tracking_config("squat"), SMALL)
    bank = ReferenceBank.from_trajectories(ROBOT, squats, config.observations.end_effectors)
    with TrackingEnv(ROBOT, bank, config, 16, seed=0, threads=1) as env:
        actor = build_actor(SMALL.finetune_ppo(), env.actor_dim, env.critic_dim, env.nu)
        untrained = copy.deepcopy(actor)
        distiller = Distiller(env, EnvExpert(env, squats, SMALL.expert), actor, SMALL, seed=0)
        distiller.total_iterations = 16
        distiller.collect()  # the expert's own rollout: a fixed validation set of labelled states
        obs, label = distiller.buffer.obs[: distiller.buffer.size].clone(), distiller.buffer.label[: distiller.buffer.size].clone()
        before = bc_loss(actor, obs, label)
        for _ in range(16):
            figures = distiller.train_iteration()
        after = bc_loss(actor, obs, label)
    assert figures["distill/expert_share"] == 0.0  # the last iterations ran the actor alone (DAgger)
    assert after < 0.2 * before  # measured 0.026 -> 0.0019 (action units squared, seeds 0-2)
    trained_error, trained_fell = tracked_joint_error(actor, squats[0])
    untrained_error, _ = tracked_joint_error(untrained, squats[0])
    assert not trained_fell
    assert trained_error < 0.2 * untrained_error  # measured 0.006 rad against 0.10-0.13 rad (seeds 0-2)


def test_label_buffer_keeps_the_newest_samples():
    buffer = LabelBuffer(5, 2, 1)
    buffer.add(np.arange(8, dtype=np.float32).reshape(4, 2), np.arange(4, dtype=np.float32)[:, None])
    buffer.add(np.arange(8, 14, dtype=np.float32).reshape(3, 2), np.arange(4, 7, dtype=np.float32)[:, None])
    assert buffer.size == 5
    assert sorted(buffer.label[:, 0].tolist()) == [2, 3, 4, 5, 6]
    obs, label = buffer.sample(64, torch.Generator().manual_seed(0))
    assert torch.equal(obs[:, 0], 2 * label[:, 0])  # pairs stay together


def test_the_expert_share_falls_to_zero_and_settings_are_checked():
    config = DistillConfig(expert_share_until=0.5)
    assert config.expert_share(0.0) == 1.0 and config.expert_share(0.25) == 0.5 and config.expert_share(0.6) == 0.0
    narrowed = distillation_tracking_config(tracking_config("walk"), DistillConfig()).randomization
    assert narrowed.delay == (0.0, 0.005) and narrowed.rough_fraction == 0.0
    assert narrowed.kp_factor == pytest.approx((0.95, 1.05)) and narrowed.friction_scale == (0.7, 1.0)
    for bad, match in ((dict(robot_range=2.0), "robot_range"), (dict(batch_size=10**7), "buffer_samples"),
                       (dict(delay=(0.01, 0.0)), "delay"), (dict(noise=1.5), "noise must be a factor in"),
                       (dict(anchor_updates=-1), "anchor_updates"), (dict(anchor_learning_rate=0.0), "anchor_learning_rate")):
        with pytest.raises(ConfigError, match=match):
            dataclasses.replace(DistillConfig(), **bad).check()


def test_ppo_after_distillation_starts_its_noise_where_the_distillation_left_it():
    task = tracking_config("walk")
    finetune = finetune_tracking_config(task, DistillConfig(noise=0.4))
    assert finetune.curriculum.factors(0.0) == pytest.approx((0.4, task.curriculum.penalty_start))
    assert finetune.curriculum.factors(1.0) == (1.0, 1.0)  # then the whole of Table II, as plain PPO
    assert finetune.randomization == task.randomization and finetune.rewards == task.rewards
    # Table II's ranges are reached over the curriculum, from about the distillation's width.
    assert finetune.curriculum.randomization_width(0.0) == 0.25 and finetune.curriculum.randomization_width(1.0) == 1.0
    paper = finetune_tracking_config(task, DistillConfig(noise=0.0, finetune_randomization=1.0))
    assert paper == task  # the paper's PPO stage: full randomization from the first iteration
    # A diagnostic PPO stage with half of Table II's noise: the same absolute noise at its start.
    half = finetune_tracking_config(task, DistillConfig(noise=0.25, finetune_noise=0.5))
    assert half.observations.noise.joint_pos == pytest.approx(0.5 * task.observations.noise.joint_pos)
    assert half.curriculum.factors(0.0)[0] == pytest.approx(0.5) and half.curriculum.factors(1.0)[0] == 1.0
    silent = finetune_tracking_config(task, DistillConfig(finetune_noise=0.0)).observations.noise
    assert all(getattr(silent, f.name) == 0.0 for f in dataclasses.fields(silent))
    with pytest.raises(ConfigError, match="finetune_noise"):
        DistillConfig(finetune_noise=2.0).check()
    with pytest.raises(ConfigError, match="finetune_randomization"):
        DistillConfig(finetune_randomization=-0.1).check()


def test_the_anchor_keeps_ppo_near_the_expert(squats):
    """PPO from an untrained actor with and without the expert anchor: the anchor labels PPO's own
    states and pulls the actor toward the expert's actions between updates."""
    config = dataclasses.replace(SMALL, anchor_learning_rate=1e-3, anchor_updates=32, batch_size=256)
    task = tracking_config("squat")
    bank = ReferenceBank.from_trajectories(ROBOT, squats, task.observations.end_effectors)

    def ppo_then_clone_loss(anchored: bool) -> tuple[float, list[dict]]:
        with TrackingEnv(ROBOT, bank, task, 16, seed=0, threads=1) as env:
            trainer = Trainer(env, config.finetune_ppo(), seed=0)
            expert = EnvExpert(env, squats, config.expert)
            if anchored:
                trainer.anchor = ExpertAnchor(expert, trainer.alg.actor, config, seed=0)
            figures = [trainer.train_iteration() for _ in range(8)]
            if anchored:  # the anchor's optimizer and generator go into the PPO checkpoint
                assert set(trainer.state()["anchor"]) == {"optimizer_state_dict", "torch_rng"}
            env.reset()  # a fixed set of expert-labelled states to score both actors on
            obs, labels = [], []
            for _ in range(20):
                action, valid = expert.act()
                obs.append(env.observations()[0][valid])
                labels.append(action[valid])
                env.step(action)
            loss = bc_loss(trainer.alg.actor, torch.from_numpy(np.concatenate(obs)).float(),
                           torch.from_numpy(np.concatenate(labels)).float())
        return loss, figures

    free, free_figures = ppo_then_clone_loss(False)
    anchored, figures = ppo_then_clone_loss(True)
    assert "anchor/loss" not in free_figures[-1]
    assert all(f["anchor/labelled_fraction"] > 0.5 for f in figures)  # the expert is valid on most states
    # The anchor's loss on PPO's own states, which move as PPO learns: one iteration against the first
    # is noisy (a reference changed at round-off moved iteration 4's ratio from 0.56 to 0.65), so the
    # mean of the last four; measured 0.42 to 0.49 of the first (seed 0, either frame loop), 0.40 and
    # 0.27 (seeds 1, 2).
    losses = [f["anchor/loss"] for f in figures]
    assert np.mean(losses[4:]) < 0.6 * losses[0]
    assert anchored < 0.3 * free  # on states of the expert's: measured 0.05 to 0.10 of it (seeds 0 to 2)


def test_a_student_distilled_on_noisy_readings_passes_less_of_their_noise_on(squats):
    """Asymmetric distillation: the expert labels from the true state, the student reads Table II's
    noise. The label's mean given noisy readings depends on them less than the label on the truth,
    so the student learns to weigh its joint readings less: under Table II's joint-position noise its
    actions vary less than those of a student distilled on exact readings."""
    students, probe = {}, None
    for noise in (0.0, 1.0):
        torch.manual_seed(0)
        settings = dataclasses.replace(SMALL, noise=noise)
        config = distillation_tracking_config(tracking_config("squat"), settings)
        bank = ReferenceBank.from_trajectories(ROBOT, squats, config.observations.end_effectors)
        with TrackingEnv(ROBOT, bank, config, 16, seed=0, threads=1) as env:
            actor = build_actor(settings.finetune_ppo(), env.actor_dim, env.critic_dim, env.nu)
            distiller = Distiller(env, EnvExpert(env, squats, settings.expert), actor, settings, seed=0)
            distiller.total_iterations = 24
            for _ in range(24):
                distiller.train_iteration()
            if probe is None:  # exact observations of the expert's states, and where the joint readings are
                env.noise_factor = 0.0
                env.reset()
                probe = (torch.from_numpy(env.observations()[0]), env.layout.actor["joint_pos_history"])
        students[noise] = Policy(actor)
    obs, history = probe
    sigma = tracking_config("squat").observations.noise.joint_pos
    generator = torch.Generator().manual_seed(1)
    spread = {}
    for noise, student in students.items():
        samples = []
        for _ in range(32):
            noisy = obs.clone()
            noisy[:, history] += sigma * torch.randn(noisy[:, history].shape, generator=generator)
            samples.append(student(noisy.numpy()))
        spread[noise] = float(np.std(np.stack(samples), axis=0).mean())
    assert spread[1.0] < 0.3 * spread[0.0], spread  # measured 0.015 against 0.20 action units


def test_a_sigterm_during_the_updates_ends_distillation_after_them_with_the_iteration_saved(squats, tmp_path):
    """SIGTERM lands inside the second iteration's Adam steps: they finish, counted and logged, and the
    distiller stops with a checkpoint of both whole iterations."""
    config = distillation_tracking_config(tracking_config("squat"), SMALL)
    bank = ReferenceBank.from_trajectories(ROBOT, squats, config.observations.end_effectors)
    with TrackingEnv(ROBOT, bank, config, 4, seed=0, threads=1) as env:
        actor = build_actor(SMALL.finetune_ppo(), env.actor_dim, env.critic_dim, env.nu)
        distiller = Distiller(env, EnvExpert(env, squats, SMALL.expert), actor, SMALL, run=tmp_path, seed=0)
        learn, learned = distiller.learn, []

        def learn_with_a_signal_inside():
            learned.append(1)
            if len(learned) == 2:
                os.kill(os.getpid(), signal.SIGTERM)
            return learn()

        distiller.learn = learn_with_a_signal_inside
        previous = signal.getsignal(signal.SIGTERM)
        processes.terminate_as_interrupt()
        try:
            with pytest.raises(KeyboardInterrupt):
                distiller.train(5, progress=False, checkpoint_every=100)
        finally:
            signal.signal(signal.SIGTERM, previous)
    assert distiller.iteration == 2 and len(learned) == 2
    saved = checkpoint.load(checkpoint.latest(tmp_path))
    assert saved["iteration"] == 2
    for name, value in actor.state_dict().items():
        assert torch.equal(saved["actor_state_dict"][name], value)
