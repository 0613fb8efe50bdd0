"""Table I: each term is `weight * kernel(error)`, computed for all worlds at once and logged by name.

Alignment (docs/envs.md): the step that applies a_t over [t, t + dt) is scored on the post-step
state against reference frame t + 1, and on the torques and contact forces applied during the step
(their means over the step's physics steps) against the reference's frame-t values, which the
record holds over [t, t + dt).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from opt2skill.envs.config import RewardConfig
from opt2skill.envs.measure import Measurement
from opt2skill.geometry import quat_error


@dataclass
class StepContext:
    """What the rewards and terminations of one step compare."""

    m: Measurement  # the post-step state and the step's mean torques and forces
    kin: dict[str, np.ndarray]  # reference frame t + 1, columns of ReferenceBank.kin
    dyn: dict[str, np.ndarray]  # reference frame t, columns of ReferenceBank.dyn
    action: np.ndarray  # a_t (N, nu), as applied (clipped)
    action_1: np.ndarray  # a_{t-1}
    action_2: np.ndarray  # a_{t-2}
    torque_limit: np.ndarray  # (N, nu) the worlds' effective torque limits


def task_errors(c: StepContext) -> dict[str, np.ndarray]:
    """Error vectors (N, d) of the tracking terms (always computed: terminations read them too)."""
    m, kin, dyn = c.m, c.kin, c.dyn
    return {
        "joint_pos": m.joint_pos - kin["joint_pos"],
        "base_pos": m.base_pos - kin["base_pos"],
        "base_ori": quat_error(kin["base_quat"], m.base_quat),
        "base_lin_vel": m.base_lin_vel - kin["base_lin_vel"],
        "base_ang_vel": m.base_ang_vel - kin["base_ang_vel"],
        "ee_pos": m.ee_pos - kin["ee_pos"],
        "joint_torque": m.torque - dyn["joint_torque"],
        "contact_force": m.force_world - dyn["force_world"],
    }


def penalty_values(c: StepContext) -> dict[str, np.ndarray]:
    return {
        "action_rate": c.action - 2.0 * c.action_1 + c.action_2,
        "torque": c.m.torque / c.torque_limit,
        "joint_acc": c.m.joint_acc,
    }


def _kernel(kind: str, scale: float, e: np.ndarray) -> np.ndarray:
    if kind == "exp_l1":
        return np.exp(-scale * np.abs(e).sum(axis=1))
    sq = np.einsum("ij,ij->i", e, e)
    return sq if kind == "sq" else np.exp(-scale * sq)


def reward_terms(config: RewardConfig, errors: dict[str, np.ndarray], penalties: dict[str, np.ndarray],
                 penalty_factor: float) -> dict[str, np.ndarray]:
    """Weighted value (N,) of every term; switched-off terms are zeros. Their sum is the reward
    (not clipped: a clip at zero would hide the penalties)."""
    out = {}
    for name, term in config.terms().items():
        e = errors[name] if name in errors else penalties[name]
        if term.weight == 0:
            out[name] = np.zeros(len(e))
            continue
        weight = term.weight * (penalty_factor if term.kernel == "sq" else 1.0)
        out[name] = weight * _kernel(term.kernel, term.scale, e)
    return out
