"""PPO settings in seconds, run identity, checkpoints: the small parts of `opt2skill.rl`."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch
from envs_support import make_env, recorded_reference

from opt2skill.envs import tracking_config
from opt2skill.errors import ConfigError, DataError
from opt2skill.rl import checkpoint
from opt2skill.rl.config import PPOConfig
from opt2skill.rl.policy import build_actor
from opt2skill.rl.run import RunSpec, config_from_dict, open_run, read_spec
from opt2skill.rl.trainer import Trainer


def test_horizons_in_seconds_become_200_hz_discounts():
    ppo = PPOConfig(discount_horizon=1.0, gae_horizon=0.25, rollout_seconds=0.24)
    dt = 0.005
    assert ppo.gamma(dt) == pytest.approx(math.exp(-0.005))
    assert ppo.gamma(dt) * ppo.lam(dt) == pytest.approx(math.exp(-0.02))
    assert ppo.steps_per_env(dt) == 48
    # the same horizons at 50 Hz give the usual 50 Hz values' order of magnitude
    assert PPOConfig(discount_horizon=2.0, gae_horizon=0.33).gamma(0.02) == pytest.approx(0.99, abs=1e-3)
    cfg = ppo.rsl_rl(dt)
    assert cfg["actor"]["hidden_dims"] == [512, 512, 256, 256] == cfg["critic"]["hidden_dims"]
    assert cfg["actor"]["obs_normalization"] and cfg["critic"]["obs_normalization"]
    assert cfg["obs_groups"] == {"actor": ["actor"], "critic": ["critic"]}
    with pytest.raises(ConfigError, match="gae_horizon"):
        PPOConfig(gae_horizon=2.0, discount_horizon=1.0).check()


def test_configs_round_trip_through_json_and_runs_refuse_another_config(tmp_path):
    config = tracking_config("walk", "pos_t", 5)
    spec = RunSpec(dataset="/d", dataset_identity={"task": "walk"}, trajectories=3, robot="digit", robot_hash="abc",
                   tracking=config, ppo=PPOConfig(), num_envs=8, seed=1)
    assert RunSpec.from_dict(spec.to_dict()) == spec
    run = tmp_path / "run"
    assert open_run(run, spec, {"command": "a"}) is False
    assert open_run(run, spec, {"command": "b"}) is True  # the same: a resume
    assert read_spec(run) == spec
    other = dataclasses.replace(spec, tracking=tracking_config("walk", "pos_t", 10), seed=2)
    with pytest.raises(ConfigError, match=r"different configuration \(seed: 1 -> 2; tracking.observations.history: 5 -> 10\)"):
        open_run(run, other, {})
    # the run and its dataset moved (another checkout): the same dataset identity and size resume there
    moved = dataclasses.replace(spec, dataset="/elsewhere/d")
    assert open_run(run, moved, {"command": "c"}) is True
    assert read_spec(run) == moved
    assert json.loads((run / "run.json").read_text())["invocations"][-1]["dataset_moved_from"] == "/d"
    with pytest.raises(ConfigError, match=r"different configuration \(trajectories: 3 -> 4\)"):
        open_run(run, dataclasses.replace(moved, dataset="/d", trajectories=4), {})
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "file").write_text("x")
    with pytest.raises(ConfigError, match="not a training run"):
        open_run(tmp_path / "busy", spec, {})
    with pytest.raises(DataError, match="unknown keys"):
        config_from_dict(PPOConfig, {"hidden": [1]})


def test_runs_made_before_adaptive_starts_still_resume_and_an_adaptive_run_is_another_config(tmp_path):
    spec = RunSpec(dataset="/d", dataset_identity={"task": "walk"}, trajectories=3, robot="digit", robot_hash="abc",
                   tracking=tracking_config("walk"), ppo=PPOConfig(), num_envs=8, seed=1)
    assert set(spec.to_dict()["tracking"]["episodes"]) == {"start_at_zero"}  # what runs before them wrote
    run = tmp_path / "run"
    open_run(run, spec, {"command": "a"})
    assert open_run(run, spec, {"command": "b"}) is True
    adaptive = dataclasses.replace(spec, tracking=tracking_config("walk", sampling="adaptive"))
    assert RunSpec.from_dict(adaptive.to_dict()) == adaptive
    with pytest.raises(ConfigError, match=r"tracking.episodes.sampling: - -> adaptive"):
        open_run(run, adaptive, {})
    assert "per_world_min" not in spec.to_dict()["tracking"]["observations"]["noise"]  # nor before --noise-min
    spread = dataclasses.replace(spec, tracking=tracking_config("walk", noise_min=0.0))
    assert RunSpec.from_dict(spread.to_dict()) == spread
    with pytest.raises(ConfigError, match=r"tracking.observations.noise.per_world_min: - -> 0.0"):
        open_run(run, spread, {})


def test_mixed_precision_reaches_rsl_rl_updates_and_is_part_of_a_runs_configuration(tmp_path):
    """`--mixed-precision`: rsl_rl's PPO updates under bf16 autocast (the networks stay float32 and the
    update moves them); runs without it write nothing new (runs made before it resume), and a resume
    that changes it is refused."""
    spec = RunSpec(dataset="/d", dataset_identity={"task": "walk"}, trajectories=3, robot="digit", robot_hash="abc",
                   tracking=tracking_config("walk"), ppo=PPOConfig(), num_envs=8, seed=1)
    assert "mixed_precision" not in spec.to_dict()["ppo"]  # what runs before it wrote
    run = tmp_path / "run"
    open_run(run, spec, {"command": "a"})
    mixed = dataclasses.replace(spec, ppo=PPOConfig(mixed_precision=True))
    assert RunSpec.from_dict(mixed.to_dict()) == mixed
    with pytest.raises(ConfigError, match=r"ppo.mixed_precision: - -> True"):
        open_run(run, mixed, {})
    traj, _ = recorded_reference(steps=30)
    trainer = Trainer(make_env([traj], num_envs=4), PPOConfig(rollout_seconds=0.02, hidden_dims=(32, 32),
                                                              mixed_precision=True), None, seed=0)
    assert trainer.alg.use_mixed_precision
    trainer.warm_up_normalizers()
    before = [p.detach().clone() for p in trainer.alg.actor.parameters()]
    figures = trainer.train_iteration()
    after = list(trainer.alg.actor.parameters())
    assert all(p.dtype == torch.float32 for p in after)
    assert any(not torch.equal(a, b) for a, b in zip(after, before)) and math.isfinite(figures["loss/surrogate"])


def test_native_bf16_is_read_from_the_cpu_flags():
    from opt2skill.rl.config import native_bf16

    zen4 = "processor\t: 0\nflags\t\t: fpu sse avx2 avx512f avx512_bf16 avx512_vnni\nbugs\t\t: sysret_ss_attrs\n"
    older = "processor\t: 0\nflags\t\t: fpu sse avx2 avx512f avx512bw\nbugs\t\t: avx512_bf16_is_not_a_flag_here\n"
    assert native_bf16(zen4) is True and native_bf16(older) is False
    assert native_bf16("flags\t\t: amx_bf16 amx_tile\n") is True


def test_train_warns_once_when_mixed_precision_would_emulate_bf16(monkeypatch, capsys):
    from pathlib import Path

    import opt2skill.rl.config as config
    from opt2skill.cli.train import _warn_emulated_bf16
    from opt2skill.rl.session import TrainRequest

    request = TrainRequest(dataset=Path("d"), out=Path("r"), mixed_precision=True)
    for native, warned in ((False, True), (True, False), (None, False)):
        monkeypatch.setattr(config, "native_bf16", lambda native=native: native)
        _warn_emulated_bf16(request)
        assert ("without native bf16" in capsys.readouterr().out) is warned
    _warn_emulated_bf16(TrainRequest(dataset=Path("d"), out=Path("r")))  # float32: nothing to say
    assert capsys.readouterr().out == ""


def test_checkpoints_are_atomic_keep_the_newest_and_restore_the_trainer(tmp_path):
    traj, _ = recorded_reference(steps=30)
    env = make_env([traj], num_envs=4)
    ppo = PPOConfig(rollout_seconds=0.02, hidden_dims=(32, 32))
    trainer = Trainer(env, ppo, tmp_path, seed=0)
    trainer.warm_up_normalizers()
    for _ in range(5):
        trainer.train_iteration()
        trainer.save()
    torn = tmp_path / "checkpoints" / "model_00000009.pt.tmp"
    torn.write_bytes(b"torn")  # an interrupted write (or one in progress)
    names = [p.name for p in checkpoint.list_checkpoints(tmp_path)]
    assert names == ["model_00000003.pt", "model_00000004.pt", "model_00000005.pt"]
    assert torn.exists()  # a reader (eval while training runs) must not delete a writer's file
    trainer.save()
    assert not torn.exists()  # the writer clears what a killed writer left
    data = checkpoint.load(checkpoint.latest(tmp_path))
    other, third = (Trainer(make_env([traj], num_envs=4, seed=s), ppo, tmp_path, seed=s) for s in (1, 2))
    other.restore(data)
    third.restore(data)
    assert (other.iteration, other.env_steps) == (5, trainer.env_steps)
    for a, b in zip(other.alg.actor.parameters(), trainer.alg.actor.parameters()):
        assert torch.equal(a, b)
    assert other.alg.optimizer.state_dict()["state"][0]["step"] == trainer.alg.optimizer.state_dict()["state"][0]["step"]
    assert torch.equal(other.alg.actor.obs_normalizer._mean, trainer.alg.actor.obs_normalizer._mean)
    # the random generators come from the checkpoint: two restores go on identically
    assert other.env.rng.bit_generator.state == third.env.rng.bit_generator.state
    assert torch.equal(other.venv.get_observations()["critic"], third.venv.get_observations()["critic"])
    assert torch.equal(torch.get_rng_state(), data["torch_rng"])
    actor = build_actor(ppo, env.actor_dim, env.critic_dim, env.nu)  # what play and export rebuild
    actor.load_state_dict(data["alg"]["actor_state_dict"])
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(DataError, match="not a readable checkpoint"):
        checkpoint.load(tmp_path / "bad.pt")
