"""Where episodes start (envs.start_sampling): uniform sampling draws exactly the starts it always
drew; adaptive sampling moves starts toward the bins where worlds failed and the second before, lets
old failures fade, survives a checkpoint, and is fed by the environment's own terminations."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from envs_support import make_env, recorded_reference

from opt2skill.envs import evaluation_config, tracking_config
from opt2skill.envs.config import EpisodeConfig
from opt2skill.envs.start_sampling import StartSampler
from opt2skill.errors import ConfigError
from opt2skill.rl.session import TrainRequest

DT = 0.005
LENGTHS = np.array([401, 801, 301])  # frames; bins of 100 frames at the default 0.5 s


def adaptive(**overrides) -> StartSampler:
    return StartSampler(EpisodeConfig(sampling="adaptive", **overrides), LENGTHS, DT)


def in_window(traj, frames, t, lo, hi) -> np.ndarray:
    return (traj == t) & (frames >= lo) & (frames < hi)


def test_uniform_sampling_draws_the_same_starts_as_before():
    for p0 in (0.0, 0.4):
        sampler = StartSampler(EpisodeConfig(start_at_zero=p0), LENGTHS, DT)
        sampler.record(np.array([1]), np.array([550]), np.array([True]))  # ignored when uniform
        rng, old = np.random.default_rng(3), np.random.default_rng(3)
        traj, frames = sampler.sample(rng, 64)
        want_traj = old.integers(0, len(LENGTHS), 64)
        want_frames = old.integers(0, LENGTHS[want_traj] - 1)
        if p0:
            want_frames = np.where(old.random(64) < p0, 0, want_frames)
        np.testing.assert_array_equal(traj, want_traj)
        np.testing.assert_array_equal(frames, want_frames)


def test_adaptive_sampling_concentrates_starts_where_worlds_failed_and_just_before():
    sampler = adaptive()
    assert sampler.num_bins == 4 + 8 + 3
    traj, frames = sampler.sample(np.random.default_rng(0), 4000)
    assert in_window(traj, frames, 1, 300, 600).mean() < 0.25  # nothing failed yet: uniform (1/8 expected)
    sampler.record(np.full(20, 1), np.full(20, 550), np.ones(20, dtype=bool))
    traj, frames = sampler.sample(np.random.default_rng(0), 20000)
    assert np.all((frames >= 0) & (frames <= LENGTHS[traj] - 2))
    # 70 % weighted, all of it in the failing bin and the two before (the 1-s look-back), plus the
    # uniform share's 1/8 of 30 %: 0.74.
    assert 0.72 < in_window(traj, frames, 1, 300, 600).mean() < 0.76
    # The failing bin weighs 1, the one before 2/3, the one before that 1/3.
    failing, before, earlier = (in_window(traj, frames, 1, lo, lo + 100).sum() for lo in (500, 400, 300))
    assert failing > before > earlier > 0.2 * failing
    assert not in_window(traj, frames, 1, 600, 800).mean() > 0.05  # after the failure: uniform share only
    assert sampler.concentration() == pytest.approx(0.5)  # the top tenth of 15 bins: the failing one, 1 of 1 + 2/3 + 1/3
    # An episode that reached its reference's end is no failure.
    quiet = adaptive()
    quiet.record(np.array([0, 2]), np.array([399, 299]), np.zeros(2, dtype=bool))
    assert quiet.score.sum() == 0


def test_old_failures_fade_as_new_ones_come():
    sampler = adaptive(half_life=500.0)
    sampler.record(np.full(10, 0), np.full(10, 150), np.ones(10, dtype=bool))  # bin 1 of reference 0
    sampler.record(np.zeros(2000, dtype=int), np.full(2000, 399), np.zeros(2000, dtype=bool))  # four half-lives
    sampler.record(np.full(5, 2), np.full(5, 250), np.ones(5, dtype=bool))  # bin 2 of reference 2
    traj, frames = sampler.sample(np.random.default_rng(1), 20000)
    new, old = in_window(traj, frames, 2, 200, 300).sum(), in_window(traj, frames, 0, 100, 200).sum()
    assert new > 4 * old  # 5 fresh failures against 10 faded to about 0.6


def test_the_failure_scores_survive_a_checkpoint_and_another_dataset_starts_afresh():
    sampler = adaptive()
    sampler.record(np.array([1, 2]), np.array([550, 10]), np.array([True, True]))
    resumed = adaptive()
    resumed.restore(sampler.state())
    np.testing.assert_array_equal(resumed.score, sampler.score)
    other = StartSampler(EpisodeConfig(sampling="adaptive"), np.array([1001]), DT)
    other.restore(sampler.state())
    assert other.score.sum() == 0


@pytest.mark.parametrize("field, value", [("sampling", "often"), ("bin_seconds", 0.0), ("uniform_share", 1.5),
                                          ("half_life", 0.0), ("lookback_seconds", -1.0)])
def test_bad_sampling_settings_get_a_clear_error(field, value):
    with pytest.raises(ConfigError, match=field.split("_")[0]):
        EpisodeConfig(**{field: value}).check()


def test_train_refuses_an_unknown_sampling(tmp_path):
    with pytest.raises(ConfigError, match="--sampling must be one of uniform, adaptive"):
        TrainRequest(dataset=tmp_path, out=tmp_path / "run", sampling="failures").check()


def test_the_environment_records_where_its_worlds_fail_and_starts_them_there():
    reference, _ = recorded_reference(steps=60)
    config = tracking_config("recorded", sampling="adaptive")
    assert config.episodes.sampling == "adaptive"
    assert evaluation_config(config).episodes.sampling == "uniform"  # evaluation starts every reference at 0
    # The recorded reference is exactly trackable; a 3-cm height limit and wild actions make worlds fail.
    config = dataclasses.replace(evaluation_config(config), episodes=EpisodeConfig(
        sampling="adaptive", bin_seconds=0.05, lookback_seconds=0.0, uniform_share=0.0),
        terminations=dataclasses.replace(config.terminations, max_height_error=0.03))
    env = make_env([reference], config, num_envs=8, seed=0)
    rng = np.random.default_rng(0)
    failed_at, steps = [], 0
    while not failed_at and steps < 60:
        result = env.step(np.clip(3.0 * rng.standard_normal((8, env.nu)), -5, 5))
        steps += 1
        if result.episodes is not None:
            failures = result.episodes.cause != 0
            failed_at += list(env.starts.score.nonzero()[0]) if failures.any() else []
    assert failed_at, "no world failed under wild actions"
    scored = set(np.flatnonzero(env.starts.score))
    env.reset()
    bins = env.start_frame // env.starts.bin_frames
    assert set(bins.tolist()) <= scored  # uniform share 0: every new start lies in a bin where a world failed


def test_worlds_a_teacher_lost_count_as_failures_where_they_stood():
    reference, _ = recorded_reference(steps=60)
    config = dataclasses.replace(tracking_config("recorded", sampling="adaptive"),
                                 episodes=EpisodeConfig(sampling="adaptive", bin_seconds=0.05, lookback_seconds=0.0))
    env = make_env([reference], config, num_envs=4, seed=0)
    frame = int(env.frame[2])
    env.fail_worlds(np.array([2]))
    assert np.flatnonzero(env.starts.score).tolist() == [min(frame, 58) // env.starts.bin_frames]
