"""Histories: N samples every `stride` policy steps, newest first, filled with the start value at a
reset; the environment's joint-position and action histories follow that rule exactly."""

from __future__ import annotations

import dataclasses

import numpy as np
from envs_support import exact_config, make_env, recorded_reference

from opt2skill.envs.history import StridedHistory


def test_strided_history_reads_newest_first_every_stride_and_reset_fills():
    h = StridedHistory(nworld=2, dim=1, samples=4, stride=3)
    h.reset(np.arange(2), np.array([[-1.0], [-2.0]]))
    for t in range(5):  # pushes 0..4
        h.push(np.array([[t], [10 + t]], dtype=float))
    np.testing.assert_array_equal(h.read(), [[4, 1, -1, -1], [14, 11, -2, -2]])
    for t in range(5, 12):
        h.push(np.array([[t], [10 + t]], dtype=float))
    np.testing.assert_array_equal(h.read(), [[11, 8, 5, 2], [21, 18, 15, 12]])
    np.testing.assert_array_equal(h.newest(1)[:, 0], [10, 20])
    h.reset(np.array([1]), np.array([[7.0]]))
    np.testing.assert_array_equal(h.read(), [[11, 8, 5, 2], [7, 7, 7, 7]])
    empty = StridedHistory(nworld=2, dim=3, samples=0, stride=4)
    empty.push(np.ones((2, 3)))
    assert empty.read().shape == (2, 0)


def test_env_histories_hold_the_measured_joints_and_actions_at_the_stride():
    traj, targets = recorded_reference(steps=40)
    config = exact_config()
    config = dataclasses.replace(config, observations=dataclasses.replace(config.observations, history=3, stride=2))
    env = make_env([traj], config)
    sl = env.layout.critic
    q_hist, a_hist = sl["joint_pos_history"], sl["action_history"]
    env.reset_worlds(np.array([0]), np.array([0]), np.array([0]))
    q0 = env.m.joint_pos[0].copy()
    held = env.actions_for_targets(q0)
    _, critic = env.observations()
    np.testing.assert_allclose(critic[0, q_hist], np.tile(q0, 3), atol=1e-6)  # cleared to the start
    np.testing.assert_allclose(critic[0, a_hist], np.tile(held, 3), atol=1e-6)
    joints, actions = [q0], []
    for k in range(7):
        a = env.actions_for_targets(targets[k][None])[0]
        result = env.step(a[None])
        joints.append(env.m.joint_pos[0].copy())
        actions.append(a)
    # after 7 steps: [q_7, q_5, q_3] and [a_6, a_4, a_2]
    np.testing.assert_allclose(result.critic[0, q_hist], np.concatenate([joints[7], joints[5], joints[3]]), atol=1e-6)
    np.testing.assert_allclose(result.critic[0, a_hist], np.concatenate([actions[6], actions[4], actions[2]]), atol=1e-6)
    # a reset clears both for the new episode; the actor's (noise-free here) history is the same
    env.reset_worlds(np.array([0]), np.array([0]), np.array([10]))
    actor, critic = env.observations()
    q_new = env.m.joint_pos[0]
    np.testing.assert_allclose(critic[0, q_hist], np.tile(q_new, 3), atol=1e-6)
    np.testing.assert_allclose(critic[0, a_hist], np.tile(env.actions_for_targets(q_new), 3), atol=1e-5)
    np.testing.assert_array_equal(actor[0, env.layout.actor["joint_pos_history"]], critic[0, q_hist])
    env.close()
