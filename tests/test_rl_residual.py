"""The residual PPO stage (`--finetune residual`) and the adaptive curriculum (`--pace adaptive`):
real squats with gains, real MuJoCo worlds, real PPO updates, the real two-stage command."""

import dataclasses
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch
from envs_support import shared_dataset
from tensordict import TensorDict

from opt2skill.deploy.export import export_policy
from opt2skill.envs import ReferenceBank, TrackingEnv, tracking_config
from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.rl import checkpoint, residual
from opt2skill.rl.distill_config import DistillConfig, finetune_tracking_config
from opt2skill.rl.distill_session import finetune_trainer, start_from_distilled, train
from opt2skill.rl.pace import AdaptivePace
from opt2skill.rl.policy import build_actor, load_policy
from opt2skill.rl.run import read_progress
from opt2skill.rl.session import TrainRequest

ROBOT = load_robot("digit")
RESIDUAL = DistillConfig(finetune="residual", residual_dims=(32, 32, 16, 16), critic_warmup_iterations=0,
                         anchor_updates=0)


@pytest.fixture(scope="module")
def squats(tmp_path_factory) -> Path:
    return shared_dataset(tmp_path_factory, "squat", 3, keep_gains=True)


def frozen_copy(actor):
    return {k: v.clone() for k, v in actor.state_dict().items()}


def test_ppo_moves_only_the_residual_and_the_action_starts_as_the_distilled_one(squats):
    from opt2skill.data.reader import Dataset

    dataset = Dataset.open(squats)
    config = finetune_tracking_config(tracking_config("squat"), RESIDUAL)
    bank = ReferenceBank.from_dataset(ROBOT, dataset, config.observations.end_effectors)
    with TrackingEnv(ROBOT, bank, config, 8, seed=0, threads=1) as env:
        torch.manual_seed(1)
        base = build_actor(RESIDUAL.student_ppo(), env.actor_dim, env.critic_dim, env.nu)
        with torch.no_grad():  # a "distilled" actor whose action is far from 0, with real statistics
            residual.linear_layers(base)[-1].weight.mul_(30.0)
        base.update_normalization(TensorDict({"actor": torch.from_numpy(env.observations()[0]).float()},
                                             batch_size=[8]))
        trainer = finetune_trainer(env, dataset, RESIDUAL, None, seed=0)
        assert trainer.ppo.hidden_dims == (544, 544, 272, 272)
        start_from_distilled(trainer, {"actor_state_dict": base.state_dict(), "elapsed": 0.0})
        actor = trainer.alg.actor
        obs = TensorDict({"actor": torch.from_numpy(env.observations()[0]).float()}, batch_size=[8])
        with torch.no_grad():
            assert base(obs).abs().mean() > 0.05
            torch.testing.assert_close(actor(obs), base(obs), atol=1e-5, rtol=1e-4)
        before = frozen_copy(actor)
        for _ in range(3):
            trainer.train_iteration()
        after = actor.state_dict()
        layers = [k for k in after if k.startswith("mlp.") and k.endswith(".weight")]
        for i, key in enumerate(layers):  # every base unit (and the output's base columns) as it was
            rows = (512, 512, 256, 256)[i] if i < 4 else None
            if rows is not None:
                assert torch.equal(after[key][:rows], before[key][:rows]), key
                assert not torch.equal(after[key][rows:], before[key][rows:]), key  # the residual learns
            else:
                assert torch.equal(after[key][:, :256], before[key][:, :256])
                assert not torch.equal(after[key][:, 256:], before[key][:, 256:])
        for key in ("obs_normalizer._mean", "obs_normalizer._var"):  # the base's statistics, kept
            assert torch.equal(after[key], before[key])
        with torch.no_grad():
            assert not torch.allclose(actor(obs), base(obs), atol=1e-6)


def test_adaptive_pace_widens_only_while_the_worlds_rarely_fail():
    pace = AdaptivePace(step=0.1, max_fall_rate=0.05, horizon=1)
    calm = {"terminations/time_out": 5.0, "terminations/fall": 0.0}
    rough = {"terminations/time_out": 0.0, "terminations/fall": 2.0, "terminations/orientation_error": 1.0,
             "terminations/xy_error": 4.0}
    assert pace.advance(0.0, calm, world_seconds=10.0) == pytest.approx(0.1)  # reference ends are no failure
    assert pace.advance(0.1, rough, world_seconds=10.0) == pytest.approx(0.1)  # 0.3 falls/s: held
    assert pace.fall_rate == pytest.approx(0.3)  # drifting off the reference is not a fall
    drifting = {"terminations/xy_error": 5.0}
    assert AdaptivePace(step=0.1, max_fall_rate=0.05).advance(0.0, drifting, 10.0) == pytest.approx(0.1)
    assert pace.advance(0.95, calm, world_seconds=10.0) == 1.0  # capped
    smoothed = AdaptivePace(step=0.1, max_fall_rate=0.05, horizon=10)
    smoothed.advance(0.0, rough, 10.0)
    assert smoothed.advance(0.0, calm, 10.0) == 0.0  # one calm iteration does not undo a bad one
    restored = AdaptivePace(step=0.1, max_fall_rate=0.05, horizon=10)
    restored.restore(smoothed.state())
    assert restored.fall_rate == smoothed.fall_rate
    for bad in ({"finetune": "lora"}, {"pace": "fast"}, {"residual_dims": (8, 8)}, {"adaptive_step": 0.0}):
        with pytest.raises(ConfigError):
            DistillConfig(**bad).check()


def test_a_residual_run_with_an_adaptive_pace_end_to_end(squats, tmp_path):
    """Both stages through the real command's API; the checkpoints of each load as policies (their
    widths read from the weights), the PPO stage's base is the distilled actor, the pace advances and
    is checkpointed, and the residual actor exports to ONNX unchanged."""
    config = dataclasses.replace(RESIDUAL, pace="adaptive", adaptive_step=0.05, adaptive_fall_rate=10.0,
                                 updates_per_iteration=2, batch_size=256, buffer_samples=5000)
    run = tmp_path / "run"
    request = TrainRequest(dataset=squats, out=run, steps=8 * 48 * 4, num_envs=8, threads=1, checkpoint_every=1,
                           command="test")
    train(request, distill_steps=8 * 24 * 3, progress=False, distill=config)
    distilled = checkpoint.load(checkpoint.latest(run / checkpoint.DISTILL_STAGE_DIR))["actor_state_dict"]
    final = checkpoint.load(checkpoint.latest(run))
    assert residual.hidden_dims(distilled) == (512, 512, 256, 256)
    assert residual.hidden_dims(final["alg"]["actor_state_dict"]) == (544, 544, 272, 272)
    assert torch.equal(final["alg"]["actor_state_dict"]["mlp.0.weight"][:512], distilled["mlp.0.weight"])
    progress = [r["curriculum/progress"] for r in read_progress(run)]
    assert progress == pytest.approx([0.0, 0.05, 0.10, 0.15])  # each iteration's world: 10 failures/s never reached
    assert final["progress"] == pytest.approx(0.2) and final["pace"]["fall_rate"] is not None

    ppo_policy, _ = load_policy(run)
    distill_policy, _ = load_policy(run, checkpoint.latest(run / checkpoint.DISTILL_STAGE_DIR))
    obs = np.random.default_rng(0).normal(size=(4, ppo_policy.obs_dim)).astype(np.float32)
    assert ppo_policy(obs).shape == distill_policy(obs).shape
    onnx_path, _ = export_policy(run, tmp_path / "policy.onnx")
    session = ort.InferenceSession(str(onnx_path))
    exported = session.run(None, {session.get_inputs()[0].name: obs})[0]
    np.testing.assert_allclose(exported, ppo_policy(obs), atol=1e-4, rtol=1e-4)
