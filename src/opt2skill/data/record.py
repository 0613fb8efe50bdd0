"""The trajectory record (docs/conventions.md): one reference motion at 200 Hz, with its metadata.

Producers (trajectory optimization) supply the state, torques and contact wrenches on the 200 Hz
grid; `build_trajectory` derives every kinematic field from them with the robot model, so derived
fields are computed one way only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from opt2skill.geometry import rotate_inv
from opt2skill.model.robot import Robot
from opt2skill.scene.description import Scene

FRAME_RATE = 200.0  # Hz
FRAME_DT = 1.0 / FRAME_RATE

# Per-frame arrays and their trailing shapes (T leads every one).
FRAME_FIELDS = (
    "time", "qpos", "qvel", "base_lin_vel", "base_ang_vel", "joint_torque",
    "contact_wrench", "contact_active", "ee_pos", "ee_pos_base", "com",
)


@dataclass
class Trajectory:
    """One reference motion. Arrays are float64 (contact_active bool), frames at 200 Hz."""

    time: np.ndarray  # (T,)
    qpos: np.ndarray  # (T, nq) MuJoCo layout
    qvel: np.ndarray  # (T, nv) MuJoCo layout
    base_lin_vel: np.ndarray  # (T, 3) body frame
    base_ang_vel: np.ndarray  # (T, 3) body frame
    joint_torque: np.ndarray  # (T, nu) held over each frame
    contact_wrench: np.ndarray  # (T, nc, 6) on the robot at each contact point, world axes
    contact_active: np.ndarray  # (T, nc) bool
    ee_pos: np.ndarray  # (T, ne, 3) world
    ee_pos_base: np.ndarray  # (T, ne, 3) base frame, relative to the base origin
    com: np.ndarray  # (T, 3) world
    task: str
    robot: str
    contact_names: tuple[str, ...]
    ee_names: tuple[str, ...]
    params: dict[str, float]
    seed: int
    solver: dict[str, Any] = field(default_factory=dict)
    validation: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    # The terrain and props the motion was made on (docs/data.md); the flat floor by default.
    scene: Scene = field(default_factory=Scene)
    # Optional solver-grid data (knot times, states in Crocoddyl's layout, controls, feedback gains):
    # name -> array. Documented in docs/data.md by the producer that writes it.
    knots: dict[str, np.ndarray] = field(default_factory=dict)
    # Where the motion comes from: "to" (trajectory optimization), "ik" (keypoints through inverse
    # kinematics), "human" (retargeted motion capture). A kinematic record (`has_dynamics=False`)
    # stores zeros as `joint_torque` and `contact_wrench`: it has no torques or contact forces.
    source: str = "to"
    has_dynamics: bool = True
    # The reference pose of each free prop of the scene (a box), name -> (T, 7): position and
    # quaternion (w, x, y, z), world. Empty when the producer gives none (docs/data.md).
    prop_poses: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return len(self.time)

    @property
    def duration(self) -> float:
        return float(self.time[-1] - self.time[0])


def build_trajectory(
    robot: Robot,
    qpos: np.ndarray,
    qvel: np.ndarray,
    joint_torque: np.ndarray,
    contact_wrench: np.ndarray,
    contact_active: np.ndarray,
    *,
    task: str,
    contact_names: tuple[str, ...],
    params: dict[str, float],
    seed: int,
    ee_names: tuple[str, ...] | None = None,
    solver: dict[str, Any] | None = None,
    provenance: dict[str, Any] | None = None,
    knots: dict[str, np.ndarray] | None = None,
    scene: Scene | None = None,
    source: str = "to",
    has_dynamics: bool = True,
    prop_poses: dict[str, np.ndarray] | None = None,
) -> Trajectory:
    """A record from 200 Hz state, torques and wrenches; kinematic fields come from the model."""
    qpos, qvel = np.asarray(qpos, dtype=float), np.asarray(qvel, dtype=float)
    n = len(qpos)
    ee_names = tuple(ee_names or robot.config.end_effectors)
    unknown = [c for c in (*contact_names, *ee_names) if c not in robot.config.end_effectors]
    if unknown:
        raise ValueError(f"contact and end-effector names must be end effectors of '{robot.name}': {unknown}")
    sites = [robot.site_id(robot.config.end_effectors[name]) for name in ee_names]
    base_body = mujoco.mj_name2id(robot.mj_model, mujoco.mjtObj.mjOBJ_BODY, robot.config.base_body)

    m = robot.mj_model
    d = mujoco.MjData(m)
    ee_pos, com = np.empty((n, len(sites), 3)), np.empty((n, 3))
    for k in range(n):
        d.qpos[:] = qpos[k]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        ee_pos[k] = d.site_xpos[sites]
        com[k] = d.subtree_com[base_body]
    quat = qpos[:, None, 3:7]
    return Trajectory(
        time=np.arange(n) * FRAME_DT,
        qpos=qpos,
        qvel=qvel,
        base_lin_vel=rotate_inv(qpos[:, 3:7], qvel[:, :3]),
        base_ang_vel=qvel[:, 3:6].copy(),
        joint_torque=np.asarray(joint_torque, dtype=float),
        contact_wrench=np.asarray(contact_wrench, dtype=float),
        contact_active=np.asarray(contact_active, dtype=bool),
        ee_pos=ee_pos,
        ee_pos_base=rotate_inv(quat, ee_pos - qpos[:, None, :3]),
        com=com,
        task=task,
        robot=robot.name,
        contact_names=tuple(contact_names),
        ee_names=ee_names,
        params=dict(params),
        seed=int(seed),
        solver=dict(solver or {}),
        provenance=dict(provenance or {}),
        knots=dict(knots or {}),
        scene=scene or Scene(),
        source=str(source),
        has_dynamics=bool(has_dynamics),
        prop_poses=checked_prop_poses(prop_poses or {}, n, scene or Scene()),
    )


def checked_prop_poses(poses: dict[str, np.ndarray], frames: int, scene: Scene) -> dict[str, np.ndarray]:
    """Prop poses as float arrays (frames, 7) with unit quaternions, each of a prop of `scene` that
    moves (a free box, a door on its hinge); a ValueError names the first that is not."""
    free = {p.name for p in scene.props if not p.fixed}
    out = {}
    for name, pose in poses.items():
        pose = np.array(pose, dtype=float)
        if name not in free:
            raise ValueError(f"prop pose '{name}' is not a moving prop of the scene (moving props: {sorted(free)})")
        if pose.shape != (frames, 7) or not np.all(np.isfinite(pose)):
            raise ValueError(f"prop pose '{name}' must be {frames} finite rows of 7 (x y z qw qx qy qz), "
                             f"got shape {pose.shape}")
        norm = np.linalg.norm(pose[:, 3:], axis=1)
        if np.any(np.abs(norm - 1.0) > 1e-6):
            raise ValueError(f"prop pose '{name}' has quaternions that are not unit (norms {norm.min():.4g} "
                             f"to {norm.max():.4g})")
        out[name] = pose
    return out
