"""Section III-B observations: named terms, their layout in each vector, and the vectors themselves.

Critic: privileged proprioception [base position, orientation, linear and angular velocity,
projected gravity, joint-position history, joint velocity, end effectors relative to the torso,
action history, contact forces, joint torques, Kp, Kd], the full reference state and, in a scene
with free props (boxes), each box's position error to its reference (privileged: the actor never
sees the box, as in the paper).
Actor: noisy proprioception [base linear and angular velocity, projected gravity, joint-position
history, joint velocity, action history] and the partial reference [base linear and angular
velocity, joint positions, contact forces, joint torques]. `layout` gives names, slices and sizes;
docs/envs.md prints them for N = 10.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from opt2skill.envs.config import ObservationConfig

# (term, source) in vector order. Sources: "m." measured (noisy for the actor), "ref." reference,
# "hist." histories, "gain." the world's effective PD gains.
ACTOR_TERMS = (
    "base_lin_vel", "base_ang_vel", "projected_gravity", "joint_pos_history", "joint_vel", "action_history",
    "ref_base_lin_vel", "ref_base_ang_vel", "ref_joint_pos", "ref_contact_force", "ref_joint_torque",
)
CRITIC_TERMS = (
    "base_pos", "base_quat", "base_lin_vel", "base_ang_vel", "projected_gravity", "joint_pos_history", "joint_vel",
    "ee_pos", "action_history", "contact_force", "joint_torque", "kp", "kd",
    "ref_base_pos", "ref_base_quat", "ref_base_lin_vel", "ref_base_ang_vel", "ref_joint_pos", "ref_joint_vel",
    "ref_ee_pos", "ref_contact_force", "ref_joint_torque", "prop_pos_error",
)


def term_sizes(config: ObservationConfig, nu: int, ncontacts: int, nprops: int = 0) -> dict[str, int]:
    """Size of every term; `ncontacts` contacts of 3 force components each (feet, hands, elbows),
    `nprops` free props (boxes) of 3 position-error components each."""
    n, ne = config.history, len(config.end_effectors)
    return {
        "base_pos": 3, "base_quat": 4, "base_lin_vel": 3, "base_ang_vel": 3, "projected_gravity": 3,
        "joint_pos_history": n * nu, "joint_vel": nu, "ee_pos": 3 * ne, "action_history": n * nu,
        "contact_force": 3 * ncontacts, "joint_torque": nu, "kp": nu, "kd": nu,
        "ref_base_pos": 3, "ref_base_quat": 4, "ref_base_lin_vel": 3, "ref_base_ang_vel": 3, "ref_joint_pos": nu,
        "ref_joint_vel": nu, "ref_ee_pos": 3 * ne,
        "ref_contact_force": 3 * ncontacts if config.reference_force else 0,
        "ref_joint_torque": nu if config.reference_torque else 0,
        "prop_pos_error": 3 * nprops,
    }


@dataclass(frozen=True)
class ObservationLayout:
    """Where each named term sits in the actor and critic vectors (terms of size 0 are left out)."""

    actor: dict[str, slice]
    critic: dict[str, slice]

    @property
    def actor_dim(self) -> int:
        return max((s.stop for s in self.actor.values()), default=0)

    @property
    def critic_dim(self) -> int:
        return max((s.stop for s in self.critic.values()), default=0)

    def rows(self, group: str) -> list[tuple[str, int, int, int]]:
        """(name, start, stop, size) of each term of `group` ('actor' or 'critic')."""
        return [(name, s.start, s.stop, s.stop - s.start) for name, s in getattr(self, group).items()]


def layout(config: ObservationConfig, nu: int, ncontacts: int, nprops: int = 0) -> ObservationLayout:
    sizes = term_sizes(config, nu, ncontacts, nprops)

    def place(terms):
        out, start = {}, 0
        for name in terms:
            if sizes[name]:
                out[name] = slice(start, start + sizes[name])
                start += sizes[name]
        return out

    return ObservationLayout(actor=place(ACTOR_TERMS), critic=place(CRITIC_TERMS))


def fill(out: np.ndarray, slices: dict[str, slice], values: dict[str, np.ndarray]) -> np.ndarray:
    """Write each term's values into its slice of the preallocated vector block `out` (N, dim)."""
    for name, s in slices.items():
        out[:, s] = values[name]
    return out
