"""Each world of the environment is built on its reference's scene; randomized ground goes on top."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest
from envs_support import ROBOT, exact_config, make_env, recorded_reference

from opt2skill.envs import ReferenceBank, TrackingEnv, tracking_config
from opt2skill.errors import ConfigError
from opt2skill.scene import Box, Scene, Stairs
from opt2skill.sim import Flat, MujocoBatchedSim, SimConfig

# Stairs going down: the squat below is made again on their top landing, 0.4 m up.
STAIRS = Scene(Stairs(0.1, start=1.0, n_steps=4, down=True))
LANDING = 0.4


@pytest.fixture(scope="module")
def recorded():
    """A squat on the flat floor, the same squat on the stairs' landing, and the targets that made it."""
    traj, targets = recorded_reference(steps=40)
    qpos = traj.qpos.copy()
    qpos[:, 2] += LANDING
    return traj, dataclasses.replace(traj, qpos=qpos, scene=STAIRS), targets


def ray_heights(model, xy):
    d = mujoco.MjData(model)
    d.qpos[0] = 30.0  # the robot out of the rays' way
    mujoco.mj_kinematics(model, d)
    hit = np.zeros(1, np.int32)
    return np.array([5.0 - mujoco.mj_ray(model, d, np.array([x, y, 5.0]), np.array([0.0, 0.0, -1.0]), None, 1, -1, hit)
                     for x, y in xy])


def test_each_world_is_its_references_scene_and_the_robot_tracks_it_there(recorded):
    flat, on_stairs, targets = recorded
    env = make_env([flat, on_stairs], exact_config(), num_envs=2)
    assert isinstance(env.terrains[0], Flat) and env.terrains[1] == STAIRS.ground and len(env.terrains) == 2
    env.reset_worlds(np.arange(2), np.array([0, 1]), np.array([0, 0]))
    np.testing.assert_array_equal(env.sim.params.terrain, [0, 1])
    np.testing.assert_array_equal(env.sim.z_offset, [0.0, 0.0])  # the reference already stands on its ground
    xy = np.stack([np.linspace(-0.95, 2.45, 35), np.full(35, 0.3)], -1)  # off the nosings
    assert np.abs(ray_heights(env.sim.models[1], xy) - STAIRS.ground_height(xy)).max() < 1e-9
    assert np.allclose(ray_heights(env.sim.models[0], xy), 0.0)
    # Both worlds follow their reference's base height: the landing holds the robot 0.4 m up.
    for k, t in enumerate(targets[:30]):
        result = env.step(env.actions_for_targets(np.tile(t, (2, 1))))
        assert result.episodes is None, k
        ref_z = np.array([flat.qpos[k + 1, 2], on_stairs.qpos[k + 1, 2]])
        assert np.abs(env.state.qpos[:, 2] - ref_z).max() < 0.01, k


def test_randomized_ground_goes_on_top_of_the_references_scene(recorded):
    flat, on_stairs, _ = recorded
    config = tracking_config("recorded")
    config = dataclasses.replace(config, randomization=dataclasses.replace(config.randomization, rough_fraction=1.0))
    env = make_env([flat, on_stairs], config, num_envs=8, seed=1)
    env.set_progress(1.0)
    assert isinstance(env.terrains[0], Flat) and env.terrains[1] == STAIRS.ground
    assert len(env.terrains) == 2 + config.randomization.rough_variants
    env.reset_worlds(np.arange(8), np.array([0, 1] * 4), np.zeros(8, dtype=int))
    params = env.sim.params
    # Flat-floor references go to the rough variants, lifted onto them; the stairs keep their stairs.
    assert np.all(params.terrain[0::2] >= 2) and np.all(params.lift[0::2])
    assert np.all(params.terrain[1::2] == 1) and not np.any(params.lift[1::2])
    assert np.all(env.sim.z_offset[1::2] == 0.0)
    assert np.abs(env.state.qpos[1::2, 2] - on_stairs.qpos[0, 2]).max() < 1e-9


def test_a_simulator_from_outside_is_refused_for_foreign_terrains_and_props(recorded):
    flat, on_stairs, _ = recorded
    with_box = dataclasses.replace(flat, scene=Scene(props=(Box(pos=(2.0, 0.0, 0.15)),)))
    config = exact_config()
    for trajectory in (on_stairs, with_box):
        bank = ReferenceBank.from_trajectories(ROBOT, [trajectory], config.observations.end_effectors)
        sim = MujocoBatchedSim(ROBOT, 1, SimConfig(nsubstep=5, nthread=1))
        with pytest.raises(ConfigError, match="can only track references made on the flat floor without props"):
            TrackingEnv(ROBOT, bank, config, 1, sim=sim)
