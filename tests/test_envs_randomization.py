"""Table II: every item sampled within its range at every reset and applied to the physics (through
the simulator's per-world models), observation noise added to the actor's inputs only, seeded
determinism, and a diverged world reset and counted while the others go on untouched."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from envs_support import ROBOT, make_env, recorded_reference

from opt2skill.envs import evaluation_config, tracking_config
from opt2skill.envs.config import nominal_ranges
from opt2skill.errors import ConfigError
from opt2skill.sim import Flat


@pytest.fixture(scope="module")
def recorded():
    return recorded_reference(steps=60)


def training_config(**randomization):
    config = tracking_config("recorded")
    return dataclasses.replace(config, randomization=dataclasses.replace(config.randomization, **randomization))


def test_every_table_ii_item_is_sampled_in_range_and_applied_at_each_reset(recorded):
    traj, _ = recorded
    env = make_env([traj], training_config(), num_envs=24, seed=3)
    cfg, sim = env.config.randomization, env.sim
    nominal = sim._nominal  # the simulator's scene (robot and terrain geoms) before randomization
    first = sim.params
    for name, (lo, hi) in cfg.ranges().items():
        value = getattr(first, name)
        if name == "mass_scale":
            value = value[:, 1:]  # body 0 is the world
        assert lo <= value.min() and value.max() <= hi, name
        assert value.std() > 0.2 * (hi - lo) / np.sqrt(12), f"{name} is not spread over its range"
    assert set(np.unique(first.terrain)) > {0}  # flat and rough both drawn
    assert isinstance(env.terrains[0], Flat) and all(not isinstance(t, Flat) for t in env.terrains[1:])
    kp, kd, limit = sim.gains()
    for w in range(sim.nworld):  # applied to each world's own model
        model = sim.models[w]
        np.testing.assert_allclose(model.body_mass[1:] / nominal.body_mass[1:], first.mass_scale[w, 1:], rtol=1e-9)
        np.testing.assert_allclose(model.opt.gravity, nominal.gravity * first.gravity_scale[w], rtol=1e-12)
        np.testing.assert_allclose(model.geom_friction, nominal.geom_friction * first.friction_scale[w], rtol=1e-12)
        np.testing.assert_allclose(model.actuator_gainprm[:, 0], kp[w], rtol=1e-12)
        np.testing.assert_allclose(kp[w], ROBOT.config.kp * first.kp_factor[w] * first.motor_strength[w], rtol=1e-12)
        np.testing.assert_allclose(-model.actuator_biasprm[:, 2], kd[w], rtol=1e-12)
        np.testing.assert_allclose(model.actuator_forcerange[:, 1], limit[w], rtol=1e-12)
    critic = env.observations()[1]  # the critic sees each world's own gains
    np.testing.assert_allclose(critic[:, env.layout.critic["kp"]], kp, rtol=1e-6)
    # resetting a world draws all of it again
    env.reset_worlds(np.array([5]))
    again = sim.params
    for name in cfg.ranges():
        assert np.all(getattr(again, name)[5] != getattr(first, name)[5]) or name == "mass_scale", name
        np.testing.assert_array_equal(getattr(again, name)[6], getattr(first, name)[6])  # others untouched
    assert np.all(again.mass_scale[5, 1:] != first.mass_scale[5, 1:])
    env.close()


def test_rough_worlds_stand_on_their_terrain_and_disabled_randomization_is_nominal(recorded):
    traj, _ = recorded
    env = make_env([traj], training_config(rough_fraction=1.0, rough_amplitude=0.05), num_envs=6, seed=1)
    assert np.all(env.sim.params.terrain > 0)
    offset = env.sim.z_offset  # the reset placed each robot on its own heightfield
    assert np.all(offset != 0) and np.all(np.abs(offset) <= 0.05) and len(np.unique(offset)) > 1
    np.testing.assert_allclose(env.m.base_pos[:, 2], traj.qpos[env.frame, 2], atol=1e-9)  # relative to the start level
    env.close()
    env = make_env([traj], training_config(enabled=False), num_envs=4, seed=1)
    params = env.sim.params
    for name in ("mass_scale", "friction_scale", "gravity_scale", "kp_factor", "kd_factor", "motor_strength"):
        np.testing.assert_array_equal(getattr(params, name), 1.0)
    np.testing.assert_array_equal(params.delay, 0.0)
    np.testing.assert_array_equal(params.terrain, 0)
    assert len(env.terrains) == 1
    env.close()


def test_the_curriculum_widens_table_ii_from_the_nominal_world(recorded):
    """With `randomization_start` 0, resets early in training draw the nominal world; halfway up the
    ramp, ranges of half the width around it; at the ramp's end, Table II in full."""
    traj, _ = recorded
    config = training_config(rough_fraction=0.5)
    config = dataclasses.replace(config, curriculum=dataclasses.replace(config.curriculum, randomization_start=0.0,
                                                                        ramp=(0.2, 0.6)))
    full = config.randomization
    env = make_env([traj], config, num_envs=64, seed=2)
    nominal = {name: (0.0 if name == "delay" else 1.0) for name in full.RANGES}
    for progress, width in ((0.0, 0.0), (0.4, 0.5), (1.0, 1.0)):
        env.set_progress(progress)
        assert env.randomization_width == pytest.approx(width)
        env.reset()
        params = env.sim.params
        for name, (lo, hi) in full.ranges().items():
            value = getattr(params, name)[:, 1:] if name == "mass_scale" else getattr(params, name)
            c = nominal[name]
            bounds = (c + width * (lo - c), c + width * (hi - c))
            assert bounds[0] - 1e-12 <= value.min() and value.max() <= bounds[1] + 1e-12, (name, progress)
            if width > 0 and hi > lo:  # spread over the narrowed range, not stuck at nominal
                assert value.max() - value.min() > 0.5 * (bounds[1] - bounds[0]), (name, progress)
        rough = np.mean(params.terrain > 0)
        assert (rough == 0) if width == 0 else (0.1 < rough < 0.5 * width + 0.2), (progress, rough)
    env.close()
    with pytest.raises(ConfigError, match="curriculum start factors"):
        dataclasses.replace(config.curriculum, randomization_start=1.5).check()
    assert full.narrowed(1.0) is full and full.narrowed(0.0).friction_scale == (1.0, 1.0)


def test_observation_noise_is_table_ii_scaled_by_the_curriculum_and_only_for_the_actor(recorded):
    traj, targets = recorded
    env = make_env([traj], training_config(enabled=False), num_envs=64, seed=0)
    noise = env.config.observations.noise
    a, c = env.layout.actor, env.layout.critic
    for progress in (1.0, 0.0):
        env.set_progress(progress)
        env.reset()  # histories refilled with readings noisy at this level
        factor = env.noise_factor
        diffs = {k: [] for k in ("base_lin_vel", "base_ang_vel", "projected_gravity", "joint_vel", "joint_pos_history")}
        for t in targets[:12]:
            result = env.step(env.actions_for_targets(np.tile(t, (64, 1))))
            for k in diffs:
                diffs[k].append(result.actor[:, a[k]] - result.critic[:, c[k]])
        sigma = {"base_lin_vel": noise.base_lin_vel, "base_ang_vel": noise.base_ang_vel,
                 "projected_gravity": noise.gravity, "joint_vel": noise.joint_vel, "joint_pos_history": noise.joint_pos}
        for k, d in diffs.items():
            measured = np.concatenate(d).std()
            if factor == 0:
                assert measured == 0, k
            else:
                assert abs(measured / (factor * sigma[k]) - 1) < 0.1, (k, measured)
    env.close()


def test_each_world_reads_its_own_share_of_the_noise_when_asked_and_evaluation_reads_it_in_full(recorded):
    traj, targets = recorded
    base = training_config(enabled=False)
    config = dataclasses.replace(base, observations=dataclasses.replace(
        base.observations, noise=dataclasses.replace(base.observations.noise, per_world_min=0.0)))
    env = make_env([traj], config, num_envs=64, seed=0)
    env.set_progress(1.0)
    env.reset_worlds(np.arange(64), np.zeros(64, dtype=int), np.zeros(64, dtype=int))  # all following the reference
    share = env._noise_share[:, 0].copy()
    assert 0 <= share.min() < 0.1 and 0.9 < share.max() <= 1 and share.std() > 0.2  # spread over [0, 1]
    a, c = env.layout.actor, env.layout.critic
    noise = env.config.observations.noise
    sigma = {"joint_vel": noise.joint_vel, "joint_pos_history": noise.joint_pos}
    diffs, shares = {k: [] for k in sigma}, {k: [] for k in sigma}
    for t in targets[1:13]:
        result = env.step(env.actions_for_targets(np.tile(t, (64, 1))))
        for k in sigma:
            diffs[k].append(result.actor[:, a[k]] - result.critic[:, c[k]])
            shares[k].append(np.repeat(env._noise_share, diffs[k][-1].shape[1], axis=1))  # a reset draws anew
    for k in sigma:
        d, s = np.concatenate(diffs[k], axis=1), np.concatenate(shares[k], axis=1)
        assert np.corrcoef(d.std(axis=1), s.mean(axis=1))[0, 1] > 0.95, k  # each world's deviation follows its share
        read = s > 0.05
        assert abs(np.std(d[read] / s[read]) / sigma[k] - 1) < 0.05, k  # and is Table II's times it
    env.reset_worlds(np.array([3]))
    assert env._noise_share[3, 0] != share[3] and np.array_equal(env._noise_share[4:, 0], share[4:])
    env.close()
    full = evaluation_config(config, noise=True)  # evaluation: Table II's noise in every world, or none
    assert full.observations.noise == base.observations.noise
    assert evaluation_config(config).observations.noise.joint_pos == 0
    with pytest.raises(ConfigError, match="per_world_min must be in"):
        dataclasses.replace(noise, per_world_min=1.5).check()
    # at the paper's setting no share is drawn: every world reads the noise in full, and the random
    # stream (so every run before the option) is unchanged
    assert np.all(make_env([traj], base, num_envs=4, seed=0)._noise_share == 1)


def test_same_seed_same_episodes_whatever_the_threads_and_another_seed_differs(recorded):
    traj, targets = recorded
    actions = np.random.default_rng(7).normal(0, 0.3, (40, 8, ROBOT.nu))

    def run(seed, threads):
        env = make_env([traj], training_config(), num_envs=8, seed=seed, threads=threads)
        env.set_progress(0.5)
        out = [env.step(env.actions_for_targets(targets[k % 60]) + actions[k]) for k in range(40)]
        env.close()
        return np.stack([o.actor for o in out]), np.stack([o.reward for o in out])

    a1, r1 = run(0, 1)
    a2, r2 = run(0, 2)
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_array_equal(r1, r2)
    a3, _ = run(1, 1)
    assert not np.array_equal(a1, a3)


def test_a_diverged_world_is_reset_and_counted_and_the_others_do_not_notice(recorded):
    traj, targets = recorded
    envs = [make_env([traj], training_config(enabled=False), num_envs=4, seed=0) for _ in range(2)]
    for env in envs:
        env.reset_worlds(np.arange(4), np.zeros(4, dtype=int), np.zeros(4, dtype=int))
    bad = envs[1]
    qpos, qvel = bad.state.qpos.copy(), bad.state.qvel.copy()
    qvel[2, 6:] = 1e6  # world 2 explodes at the next step
    bad.sim.reset(np.array([2]), qpos[2:3], qvel[2:3], targets=qpos[2:3, 7:])
    results = [env.step(env.actions_for_targets(np.tile(targets[0], (4, 1)))) for env in envs]
    good, broken = results
    assert broken.unstable == 1 and good.unstable == 0
    assert broken.terminated[2] and not broken.truncated[2] and broken.reward[2] == 0
    assert broken.episodes.cause[list(broken.episodes.worlds).index(2)] == 5  # CAUSES[5] == "unstable"
    assert np.all(np.isfinite(broken.actor)) and np.all(np.isfinite(broken.critic))
    assert np.abs(bad.state.qvel[2]).max() < 10  # a fresh episode
    others = [0, 1, 3]
    np.testing.assert_array_equal(broken.critic[others], good.critic[others])
    np.testing.assert_array_equal(broken.reward[others], good.reward[others])
    for env in envs:
        env.close()


def test_pushes_change_the_base_velocity_within_their_range_on_their_schedule(recorded):
    traj, targets = recorded
    config = training_config(push_speed=0.5, push_interval=(0.05, 0.1), **nominal_ranges(tracking_config("x").randomization))
    env = make_env([traj], config, num_envs=16, seed=5)
    env.reset_worlds(np.arange(16), np.zeros(16, dtype=int), np.zeros(16, dtype=int))
    hold = np.tile(env.actions_for_targets(targets[0]), (16, 1))
    pushed, kicks = 0, []
    for _ in range(40):
        before = env.state.qvel[:, :3].copy()
        countdown = env._push_countdown.copy()
        result = env.step(hold)
        due = countdown == 1  # these worlds were pushed at the start of this step
        assert result.pushed == due.sum()
        pushed += result.pushed
        if due.any():
            # the 5 ms step after a push changes the base velocity by about the push (gravity and contact aside)
            kicks.append(np.linalg.norm((env.state.qvel[due, :2] - before[due, :2]), axis=1))
    kicks = np.concatenate(kicks)
    assert pushed >= 16 * 40 // 20 // 2  # every 10-20 steps per world
    assert kicks.max() <= 0.5 + 0.1 and kicks.mean() > 0.1


def test_pushes_are_off_in_the_nominal_evaluation_and_scale_with_the_curriculum():
    config = tracking_config("walk")
    assert config.randomization.push_speed > 0  # training pushes by default (Section III-B)
    assert evaluation_config(config).randomization.push_speed == 0
    assert evaluation_config(config, randomize=True, noise=True).randomization.push_speed == 0
    assert evaluation_config(config, pushes=True).randomization.push_speed == config.randomization.push_speed
    assert config.randomization.narrowed(0.5).push_speed == pytest.approx(0.5 * config.randomization.push_speed)
    with pytest.raises(ConfigError, match="push_speed"):
        training_config(push_speed=-1).check()
    with pytest.raises(ConfigError, match="push_interval"):
        training_config(push_interval=(3.0, 1.0)).check()


def test_kp_scale_softens_every_servo_of_every_world(recorded):
    traj, _ = recorded
    base = training_config()
    soft = dataclasses.replace(base, actions=dataclasses.replace(base.actions, kp_scale=0.4))
    env = make_env([traj], soft, num_envs=6, seed=2)
    kp, kd, _ = env.sim.gains()
    params = env.sim.params
    np.testing.assert_allclose(kp, ROBOT.config.kp * params.kp_factor * params.motor_strength, rtol=1e-12)
    assert np.all(params.kp_factor >= 0.4 * 0.9 - 1e-12) and np.all(params.kp_factor <= 0.4 * 1.1 + 1e-12)
    np.testing.assert_allclose(kd, ROBOT.config.kd * params.kd_factor * params.motor_strength, rtol=1e-12)
    with pytest.raises(ConfigError, match="kp_scale"):
        dataclasses.replace(base, actions=dataclasses.replace(base.actions, kp_scale=0.0)).check()
