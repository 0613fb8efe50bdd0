"""Rewards and their timing: a reference recorded from the simulator, replayed with the same PD
targets, is tracked exactly, so every task term must give its full weight; the same motion against a
reference one frame off must not."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from envs_support import ROBOT, exact_config, make_env, recorded_reference

from opt2skill.envs import tracking_config
from opt2skill.envs.config import RewardConfig

TASK_TERMS = ("joint_pos", "base_pos", "base_ori", "base_lin_vel", "base_ang_vel", "ee_pos", "joint_torque",
              "contact_force")


@pytest.fixture(scope="module")
def recorded():
    return recorded_reference(steps=60)


def replay(env, targets):
    """Step the env with the actions that give `targets`; per-step term values (steps, term)."""
    env.reset_worlds(np.array([0]), np.array([0]), np.array([0]))
    env.set_progress(1.0)
    rows = []
    for t in targets:
        result = env.step(env.actions_for_targets(t[None]))
        assert not (result.terminated[0] or result.unstable)
        rows.append({k: float(v[0]) for k, v in result.terms.items()} | {"total": float(result.reward[0])})
        if result.truncated[0]:
            break
    return rows


def independent_penalties(env, traj, targets):
    """The penalties of step k computed from the recorded arrays, not by the environment."""
    cfg = env.config.rewards
    a = env.actions_for_targets(targets)
    held = env.actions_for_targets(traj.qpos[0, 7:])
    a_prev = np.vstack([held, held, a])  # a_{k-2}, a_{k-1}, a_k for k = 0.. (the reset holds the start)
    rate = a_prev[2:] - 2 * a_prev[1:-1] + a_prev[:-2]
    limit = ROBOT.config.torque_limit
    acc = np.diff(traj.qvel[:, 6:], axis=0) / 0.005
    return {
        "action_rate": cfg.action_rate.weight * (rate ** 2).sum(1),
        "torque": cfg.torque.weight * ((traj.joint_torque[:-1] / limit) ** 2).sum(1),
        "joint_acc": cfg.joint_acc.weight * (acc ** 2).sum(1),
    }


def test_exact_tracking_scores_every_task_weight_and_the_total_adds_the_penalties(recorded):
    traj, targets = recorded
    env = make_env([traj])
    rows = replay(env, targets)
    assert len(rows) == len(targets)  # the episode ends exactly at the reference's last frame
    weights = {name: term.weight for name, term in RewardConfig().terms().items()}
    for name in TASK_TERMS:
        values = np.array([r[name] for r in rows])
        np.testing.assert_allclose(values, weights[name], rtol=1e-5, err_msg=name)
    penalties = independent_penalties(env, traj, targets)
    for name, expected in penalties.items():
        np.testing.assert_allclose([r[name] for r in rows], expected, rtol=1e-6, atol=1e-12, err_msg=name)
    assert min(penalties["action_rate"]) < 0 and min(penalties["joint_acc"]) < 0  # not trivially zero
    total = np.array([r["total"] for r in rows])
    np.testing.assert_allclose(total, sum(weights[n] for n in TASK_TERMS) + sum(penalties.values()), rtol=1e-6)
    env.close()


def test_total_is_the_sum_of_task_weights_with_penalties_off_and_walking_drops_base_position(recorded):
    traj, targets = recorded
    off = dataclasses.replace(RewardConfig(), **{n: dataclasses.replace(getattr(RewardConfig(), n), weight=0.0)
                                                 for n in ("action_rate", "torque", "joint_acc")})
    for task, expected in (("squat", 2.0), ("walk", 1.7)):
        rewards = dataclasses.replace(off, base_pos=tracking_config(task).rewards.base_pos)
        env = make_env([traj], exact_config(rewards=rewards))
        total = np.array([r["total"] for r in replay(env, targets)])
        np.testing.assert_allclose(total, expected, rtol=1e-5)
        env.close()


def test_a_reference_one_frame_off_scores_less(recorded):
    """The alignment matters: states compared with frame t (not t + 1), or torques and forces with
    frame t + 1 (not t), lose reward at once."""
    traj, targets = recorded
    late_state = dataclasses.replace(traj, qpos=np.vstack([traj.qpos[:1], traj.qpos[:-1]]),
                                     qvel=np.vstack([traj.qvel[:1], traj.qvel[:-1]]))
    early_forces = dataclasses.replace(traj, joint_torque=np.vstack([traj.joint_torque[1:], traj.joint_torque[-1:]]),
                                       contact_wrench=np.vstack([traj.contact_wrench[1:], traj.contact_wrench[-1:]]))
    env = make_env([late_state])
    rows = replay(env, targets)
    # exact tracking is within 1e-5 of the weights (test above); one frame late costs 10 times more
    assert np.mean([r["joint_pos"] for r in rows]) < 0.3 * (1 - 1e-4)
    assert np.mean([r["base_ori"] for r in rows]) < 0.3 * (1 - 1e-4)
    env.close()
    env = make_env([early_forces])
    rows = replay(env, targets)
    assert np.mean([r["joint_torque"] for r in rows]) < 0.095
    assert np.mean([r["contact_force"] for r in rows]) < 0.095
    env.close()


def test_penalties_follow_the_curriculum_and_the_total_is_not_clipped(recorded):
    traj, targets = recorded
    env = make_env([traj])
    rough = targets + np.random.default_rng(0).normal(0, 0.2, targets.shape)  # a jerky policy
    env.reset_worlds(np.array([0]), np.array([0]), np.array([0]))
    env.set_progress(1.0)
    full = env.step(env.actions_for_targets(rough[:1])).terms["action_rate"][0]
    env.reset_worlds(np.array([0]), np.array([0]), np.array([0]))
    env.set_progress(0.0)
    start = env.config.curriculum.penalty_start
    early = env.step(env.actions_for_targets(rough[:1])).terms["action_rate"][0]
    np.testing.assert_allclose(early, start * full, rtol=1e-9)
    env.set_progress(1.0)
    totals = [env.step(env.actions_for_targets(t[None])).reward[0] for t in rough[1:30]]
    assert min(totals) < 0  # penalties can outweigh the task terms: nothing clips the sum at zero
    env.close()
