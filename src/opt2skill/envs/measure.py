"""What the task reads from a simulator step, in the frames the record uses (docs/conventions.md).

Computed once per policy step for all worlds; the rows of reset worlds are then replaced by their
reset readings, so rewards see the step's outcome and observations the state the policy acts from.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from opt2skill.geometry import quat_to_mat
from opt2skill.sim.base import SimStep


@dataclass
class Measurement:
    base_pos: np.ndarray  # (N, 3) world, z relative to the world's start level (sim z_offset)
    base_quat: np.ndarray  # (N, 4) w x y z, w >= 0
    base_lin_vel: np.ndarray  # (N, 3) body frame
    base_ang_vel: np.ndarray  # (N, 3) body frame
    gravity: np.ndarray  # (N, 3) unit gravity direction, body frame
    joint_pos: np.ndarray  # (N, nu) END
    joint_vel: np.ndarray  # (N, nu) END
    joint_acc: np.ndarray  # (N, nu) MEAN over the step
    ee_pos: np.ndarray  # (N, 3 ne) torso-relative, base frame, END
    torque: np.ndarray  # (N, nu) MEAN over the step (what the reference's held frame-t torque is compared with)
    force_world: np.ndarray  # (N, 3 ncontacts) MEAN force on each of the references' contacts, world axes
    force_heading: np.ndarray  # (N, 3 ncontacts) the same, in the base's heading (yaw) frame
    contact: np.ndarray  # (N, ncontacts) bool, LAST: the contact touches something

    def assign(self, rows: np.ndarray, other: Measurement) -> None:
        for f in fields(self):
            getattr(self, f.name)[rows] = getattr(other, f.name)


@dataclass
class Readings:
    """The proprioception the actor was given with its latest observation, noise included (equal to
    the true values where the noise is 0): what a controller that sees what the actor sees reads."""

    joint_pos: np.ndarray  # (N, nu) the newest joint-position sample of the history
    joint_vel: np.ndarray  # (N, nu)
    base_lin_vel: np.ndarray  # (N, 3) body frame
    base_ang_vel: np.ndarray  # (N, 3) body frame
    gravity: np.ndarray  # (N, 3) projected gravity, body frame (not renormalized)


def measure(out: SimStep, z_offset: np.ndarray, ee_index: np.ndarray, contact_rows: np.ndarray) -> Measurement:
    """Measurement of a step's (or a reset's) outputs; `ee_index` selects the tracked end effectors,
    `contact_rows` the references' contacts among the feet then the point contacts
    (`SensorLayout.contact_rows`)."""
    n = len(out.qpos)
    quat = out.qpos[:, 3:7]
    rot = quat_to_mat(quat)  # body -> world
    base_pos = out.qpos[:, :3].copy()
    base_pos[:, 2] -= z_offset
    rel = out.ee_pos[:, ee_index] - out.qpos[:, None, :3]
    force = np.concatenate([out.contact_wrench_mean[:, :, :3], out.point_force_mean], axis=1)[:, contact_rows]
    found = np.concatenate([out.contact_found, out.point_found], axis=1)[:, contact_rows]
    c, s = rot[:, 0, 0], rot[:, 1, 0]  # heading direction (cos, sin) up to a positive factor
    norm = np.sqrt(c * c + s * s)
    norm[norm < 1e-9] = 1.0
    c, s = (c / norm)[:, None], (s / norm)[:, None]
    heading = np.stack([c * force[..., 0] + s * force[..., 1], -s * force[..., 0] + c * force[..., 1], force[..., 2]], -1)
    return Measurement(
        base_pos=base_pos,
        base_quat=np.where(quat[:, :1] < 0, -quat, quat),
        base_lin_vel=np.einsum("nji,nj->ni", rot, out.qvel[:, :3]),
        base_ang_vel=out.qvel[:, 3:6].copy(),
        gravity=-rot[:, 2, :],  # R^T (0, 0, -1)
        joint_pos=out.joint_pos,
        joint_vel=out.joint_vel,
        joint_acc=out.joint_acc,
        ee_pos=np.einsum("nji,nkj->nki", rot, rel).reshape(n, -1),
        torque=out.torque_mean,
        force_world=force.reshape(n, -1),
        force_heading=heading.reshape(n, -1),
        contact=found > 0,
    )
