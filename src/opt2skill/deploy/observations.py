"""The actor's observation, built robot-side from sensor readings and the reference, as the policy's
metadata describes it. Written independently of the training environment (nothing of `envs` is
imported): `tests/test_deploy_player.py` checks that both build the same vector from the same states.

Each term name has a meaning fixed here (`TERMS`: what it is and in which frame); the metadata says
where each term sits, how long the histories are and which reference frame the reference terms
read. A term this code does not know is an error, never a silent zero.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from opt2skill.deploy.metadata import PolicyMetadata
from opt2skill.errors import DataError
from opt2skill.eval.references import check_contacts
from opt2skill.geometry import yaw_of

# name -> what it is (frames as docs/conventions.md). Sizes come from the metadata.
TERMS = {
    "base_lin_vel": "base linear velocity, base frame (m/s): the state estimator's (in simulation the IMU velocimeter at the base origin)",
    "base_ang_vel": "base angular velocity, base frame (rad/s): the IMU gyro",
    "projected_gravity": "unit gravity direction in the base frame, from the IMU orientation",
    "joint_pos_history": "joint positions (rad), history: N samples every `stride` policy steps, newest (now) first",
    "joint_vel": "joint velocities (rad/s)",
    "action_history": "previous actions (policy units), history: a_{t-1}, a_{t-1-stride}, ..., N samples",
    "ref_base_lin_vel": "reference base linear velocity, base frame, frame t + reference.offset",
    "ref_base_ang_vel": "reference base angular velocity, base frame, frame t + reference.offset",
    "ref_joint_pos": "reference joint positions, frame t + reference.offset",
    "ref_contact_force": "reference force on each contact (3 per contact, in robot.contacts order: feet, hands, "
                         "elbows as the references have them), frame t, in the reference's heading frame (world "
                         "axes turned by the reference base yaw)",
    "ref_joint_torque": "reference joint torques (N m), frame t (held over [t, t + dt))",
}
KINEMATIC = ("ref_base_lin_vel", "ref_base_ang_vel", "ref_joint_pos")
DYNAMIC = ("ref_contact_force", "ref_joint_torque")


@dataclass
class Readings:
    """What the robot measures at one instant (after any sensor noise)."""

    gravity: np.ndarray  # (3,) unit gravity direction in the base frame (from the IMU orientation)
    base_lin_vel: np.ndarray  # (3,) base frame
    base_ang_vel: np.ndarray  # (3,) base frame
    joint_pos: np.ndarray  # (nu,)
    joint_vel: np.ndarray  # (nu,)


class ReferenceFrames:
    """The reference quantities the actor reads, per 200 Hz frame, from a trajectory record."""

    def __init__(self, traj, contacts: list[str]):
        check_contacts(traj.contact_names, contacts, "the reference")
        self.num_frames = traj.num_frames
        self.base_lin_vel = traj.base_lin_vel
        self.base_ang_vel = traj.base_ang_vel
        self.joint_pos = traj.qpos[:, 7:]
        self.joint_torque = traj.joint_torque
        quat = traj.qpos[:, 3:7] / np.linalg.norm(traj.qpos[:, 3:7], axis=1, keepdims=True)
        yaw = yaw_of(quat)
        force = traj.contact_wrench[:, :, :3]
        c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        self.force_heading = np.stack([c * force[..., 0] + s * force[..., 1], -s * force[..., 0] + c * force[..., 1],
                                       force[..., 2]], axis=-1).reshape(len(yaw), -1)


class History:
    """The last `depth` pushed vectors; `read` gives N of them `stride` apart, newest first."""

    def __init__(self, samples: int, stride: int):
        self.samples, self.stride = samples, stride
        self.items: deque[np.ndarray] = deque(maxlen=max((samples - 1) * stride + 1, 1))

    def fill(self, values: np.ndarray) -> None:
        """Start over as if `values` had been pushed to every slot: one vector (dim,) repeated, or one
        per slot (depth, dim), oldest first."""
        values = np.asarray(values, dtype=float)
        rows = np.broadcast_to(values, (self.items.maxlen, values.shape[-1])) if values.ndim == 1 else values
        self.items.clear()
        self.items.extend(np.array(r) for r in rows)

    def push(self, value: np.ndarray) -> None:
        self.items.append(np.array(value, dtype=float))

    def read(self) -> np.ndarray:
        newest = len(self.items) - 1
        return np.concatenate([self.items[newest - k * self.stride] for k in range(self.samples)]) if self.samples else np.zeros(0)


class ActorObservation:
    """Builds the actor's input vector from readings, histories and a reference."""

    def __init__(self, meta: PolicyMetadata):
        unknown = [t.name for t in meta.terms if t.name not in TERMS]
        if unknown:
            raise DataError(f"the policy observes terms this player does not know: {unknown} (known: {list(TERMS)})")
        h = meta.history
        self.meta = meta
        self.terms = meta.terms
        self.offset = int(meta.reference["offset"])
        self.joint_pos = History(int(h["samples"]), int(h["stride"]))
        self.actions = History(int(h["samples"]), int(h["stride"]))
        self.depth = self.joint_pos.items.maxlen

    def reset(self, joint_pos: np.ndarray, held_action: np.ndarray) -> None:
        """A new episode: the joint-position history holds the start reading(s) (`joint_pos` (nu,) or
        one independent reading per slot (depth, nu)), the action history the action that holds
        the start pose."""
        self.joint_pos.fill(joint_pos)
        self.actions.fill(held_action)

    def push(self, joint_pos: np.ndarray, action: np.ndarray) -> None:
        """After a policy step: the new joint reading and the action that was applied."""
        self.joint_pos.push(joint_pos)
        self.actions.push(action)

    def observe(self, r: Readings, ref: ReferenceFrames, t: int) -> np.ndarray:
        """The observation at policy step t (the reference's frame t is the current instant)."""
        k = min(t + self.offset, ref.num_frames - 1)
        values = {
            "base_lin_vel": r.base_lin_vel, "base_ang_vel": r.base_ang_vel,
            "projected_gravity": r.gravity, "joint_vel": r.joint_vel,
            "joint_pos_history": self.joint_pos.read(), "action_history": self.actions.read(),
            "ref_base_lin_vel": ref.base_lin_vel[k], "ref_base_ang_vel": ref.base_ang_vel[k],
            "ref_joint_pos": ref.joint_pos[k], "ref_contact_force": ref.force_heading[t],
            "ref_joint_torque": ref.joint_torque[t],
        }
        obs = np.empty(self.meta.obs_dim, dtype=np.float32)
        for term in self.terms:
            value = np.asarray(values[term.name]).ravel()
            if value.size != term.size:
                raise DataError(f"observation term '{term.name}' has {value.size} values here; the policy expects {term.size}")
            obs[term.start:term.stop] = value
        return obs
