"""Reference frames the tracking task reads: every trajectory of a dataset in two float32 matrices.

`kin` holds what a frame's state is (base pose and velocities, joints, end effectors), `dyn` what
acts over the frame's step (joint torques, the forces at the references' contacts, `contact_names`). One row per frame, trajectories
stacked: reading the frames of all worlds is one gather per matrix. docs/envs.md has the columns.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from opt2skill.data.reader import Dataset
from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.errors import DataError
from opt2skill.geometry import quat_to_mat, yaw_of
from opt2skill.model.robot import Robot
from opt2skill.scene.description import Scene
from opt2skill.scene.slots import moving
from opt2skill.scene.terrain import Terrain

FIELDS = ("qpos", "qvel", "base_lin_vel", "base_ang_vel", "joint_torque", "contact_wrench", "ee_pos_base")


def _slices(sizes: dict[str, int]) -> dict[str, slice]:
    out, start = {}, 0
    for name, size in sizes.items():
        out[name] = slice(start, start + size)
        start += size
    return out


@dataclass
class ReferenceBank:
    kin: np.ndarray  # (rows, dk) float32, columns `kin_cols`
    dyn: np.ndarray  # (rows, dd) float32, columns `dyn_cols`
    kin_cols: dict[str, slice]
    dyn_cols: dict[str, slice]
    start: np.ndarray  # (n,) first row of each trajectory
    length: np.ndarray  # (n,) frames of each
    positions: np.ndarray  # (n,) dataset positions (or list positions) of the trajectories
    task: str
    xy_range: tuple[tuple[float, float], tuple[float, float]]  # extent of the base paths, for terrain
    scenes: tuple[Scene, ...]  # (n,) the scene each trajectory was made on
    # (rows, nmoving, 7) reference pose of each moving prop slot per row (x y z, quaternion w x y z):
    # a trajectory's boxes in its scene's order, then its doors (their hinge frames), from the
    # record's `prop_poses` (its scene pose where the record has none); slots its scene does not
    # fill hold the identity at the origin.
    prop_pose: np.ndarray
    contact_names: tuple[str, ...]  # the references' contacts (feet, hands, elbows), the order of their forces
    # False for kinematic references (IK, retargeted human motion): their torques and contact forces
    # are zeros, so only the Pos inputs may be used (`envs.config.check_reference_inputs`).
    has_dynamics: bool = True
    source: str = "to"

    @property
    def num_trajectories(self) -> int:
        return len(self.start)

    @property
    def num_rows(self) -> int:
        return len(self.kin)

    @classmethod
    def from_dataset(cls, robot: Robot, dataset: Dataset, end_effectors: Sequence[str],
                     subset: Sequence[int] | None = None, use_cache: bool = True) -> ReferenceBank:
        if len(dataset) == 0:
            raise DataError(f"dataset {dataset.root} has no accepted trajectories to track")
        identity = dataset.identity
        if identity.get("robot_hash") not in (None, robot.hash):
            raise DataError(
                f"dataset {dataset.root} was made for robot '{identity.get('robot')}' with a different robot "
                f"file (hash {str(identity.get('robot_hash'))[:12]}); this run uses '{robot.name}' ({robot.hash[:12]})"
            )
        first = dataset.meta(0 if subset is None else int(subset[0]))
        table = dataset.frame_table(FIELDS, dtype=np.float32, subset=subset, use_cache=use_cache)
        scenes = [dataset.meta(int(p)).scene for p in table.trajectories]
        poses = [dataset.prop_poses(int(p)) if any(not q.fixed for q in s.props) else {}
                 for p, s in zip(table.trajectories, scenes)]
        return cls._build(robot, dict(table.fields), table.start, table.length, table.trajectories,
                          identity.get("task", first.task), first.contact_names, first.ee_names, end_effectors,
                          scenes, poses, has_dynamics=first.has_dynamics, source=first.source)

    @classmethod
    def from_trajectories(cls, robot: Robot, trajectories: Sequence[Trajectory], end_effectors: Sequence[str],
                          dtype=np.float32) -> ReferenceBank:
        if not trajectories:
            raise DataError("no trajectories to track")
        first = trajectories[0]
        for t in trajectories:
            if t.contact_names != first.contact_names or t.ee_names != first.ee_names:
                raise DataError("reference trajectories must share their contact and end-effector names")
        length = np.array([t.num_frames for t in trajectories], dtype=np.int64)
        fields = {name: np.concatenate([getattr(t, name) for t in trajectories]).astype(dtype) for name in FIELDS}
        start = np.concatenate([[0], np.cumsum(length)[:-1]])
        return cls._build(robot, fields, start, length, np.arange(len(trajectories)), first.task,
                          first.contact_names, first.ee_names, end_effectors, [t.scene for t in trajectories],
                          [t.prop_poses for t in trajectories], dtype,
                          has_dynamics=all(t.has_dynamics for t in trajectories),
                          source=first.source if len({t.source for t in trajectories}) == 1 else "mixed")

    @classmethod
    def _build(cls, robot: Robot, f: dict[str, np.ndarray], start, length, positions, task: str,
               contact_names: Sequence[str], ee_names: Sequence[str], end_effectors: Sequence[str],
               scenes: Sequence[Scene], prop_poses: Sequence[dict[str, np.ndarray]], dtype=np.float32,
               has_dynamics: bool = True,
               source: str = "to") -> ReferenceBank:
        nu, nq = robot.nu, robot.nq
        if f["qpos"].shape[1] != nq or f["joint_torque"].shape[1] != nu:
            raise DataError(f"reference trajectories have {f['qpos'].shape[1]} positions and {f['joint_torque'].shape[1]} "
                            f"torques; robot '{robot.name}' has {nq} and {nu}")
        if np.any(length < 2):
            raise DataError("every reference trajectory needs at least 2 frames")
        unknown = [c for c in contact_names if c not in robot.config.end_effectors]
        if unknown or len(set(contact_names)) != len(contact_names):
            raise DataError(f"the references' contacts {list(contact_names)} must be distinct end effectors of "
                            f"robot '{robot.name}' ({list(robot.config.end_effectors)})")
        missing = [e for e in end_effectors if e not in ee_names]
        if missing:
            raise DataError(f"end effectors {missing} are not in the references (they have {list(ee_names)})")
        ee = [list(ee_names).index(e) for e in end_effectors]
        qpos = f["qpos"]
        quat = qpos[:, 3:7] / np.linalg.norm(qpos[:, 3:7], axis=1, keepdims=True)
        force = f["contact_wrench"][:, :, :3]  # (rows, ncontacts, 3) on the robot, world axes
        yaw = yaw_of(quat)
        c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        heading = np.stack([c * force[..., 0] + s * force[..., 1], -s * force[..., 0] + c * force[..., 1],
                            force[..., 2]], axis=-1)  # R_z(yaw)^T F
        rows = len(qpos)
        kin_parts = {
            "base_pos": qpos[:, :3], "base_quat": quat, "base_lin_vel": f["base_lin_vel"],
            "base_ang_vel": f["base_ang_vel"], "joint_pos": qpos[:, 7:], "joint_vel": f["qvel"][:, 6:],
            "ee_pos": f["ee_pos_base"][:, ee].reshape(rows, -1),
        }
        dyn_parts = {
            "joint_torque": f["joint_torque"], "force_world": force.reshape(rows, -1),
            "force_heading": heading.reshape(rows, -1),
        }
        kin_cols = _slices({k: v.shape[1] for k, v in kin_parts.items()})
        dyn_cols = _slices({k: v.shape[1] for k, v in dyn_parts.items()})
        kin = np.concatenate(list(kin_parts.values()), axis=1).astype(dtype)
        dyn = np.concatenate(list(dyn_parts.values()), axis=1).astype(dtype)
        if not (np.all(np.isfinite(kin)) and np.all(np.isfinite(dyn))):
            raise DataError("reference trajectories contain non-finite values")
        xy = qpos[:, :2]
        xy_range = ((float(xy[:, 0].min()), float(xy[:, 0].max())), (float(xy[:, 1].min()), float(xy[:, 1].max())))
        return cls(kin, dyn, kin_cols, dyn_cols, np.asarray(start, dtype=np.int64), np.asarray(length, dtype=np.int64),
                   np.asarray(positions), str(task), xy_range, tuple(scenes),
                   _prop_rows(scenes, prop_poses, np.asarray(length), dtype), tuple(contact_names),
                   bool(has_dynamics), str(source))

    def grounds(self) -> tuple[list[Terrain], np.ndarray]:
        """The distinct grounds the trajectories were made on (in order of first use) and the index
        (n,) of each trajectory's ground among them."""
        first: dict = {}  # terrain description -> its first scene (whose ground is then built once)
        for scene in self.scenes:
            first.setdefault(scene.terrain, scene)
        position = {terrain: i for i, terrain in enumerate(first)}
        return [s.ground for s in first.values()], np.array([position[s.terrain] for s in self.scenes], dtype=np.int64)

    def prop_sets(self) -> tuple[list[tuple], np.ndarray]:
        """The distinct prop sets of the trajectories' scenes (in order of first use) and the index
        (n,) of each trajectory's set."""
        sets: dict = {}
        for scene in self.scenes:
            sets.setdefault(scene.props, len(sets))
        return list(sets), np.array([sets[s.props] for s in self.scenes], dtype=np.int64)

    def prop_state(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Moving props' poses (k, nmoving, 7) and velocities (k, nmoving, 6), float64, of reference rows
        that have a next row: the linear velocity by finite difference to it, the angular zero."""
        pose = self.prop_pose[rows].astype(np.float64)
        vel = np.zeros((*pose.shape[:2], 6))
        vel[..., :3] = (self.prop_pose[np.asarray(rows) + 1, :, :3] - pose[..., :3]) / FRAME_DT
        return pose, vel

    def state(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """MuJoCo qpos (k, nq) and qvel (k, nv), float64, of reference rows (base linear velocity to
        the world frame, quaternion normalized)."""
        k = self.kin[rows].astype(np.float64)
        cols = self.kin_cols
        quat = k[:, cols["base_quat"]]
        quat /= np.linalg.norm(quat, axis=1, keepdims=True)
        lin_world = np.einsum("kij,kj->ki", quat_to_mat(quat), k[:, cols["base_lin_vel"]])
        qpos = np.concatenate([k[:, cols["base_pos"]], quat, k[:, cols["joint_pos"]]], axis=1)
        qvel = np.concatenate([lin_world, k[:, cols["base_ang_vel"]], k[:, cols["joint_vel"]]], axis=1)
        return qpos, qvel


def _prop_rows(scenes: Sequence[Scene], poses: Sequence[dict[str, np.ndarray]], length: np.ndarray,
               dtype) -> np.ndarray:
    """(rows, nmoving, 7) moving props' poses of stacked trajectories (`ReferenceBank.prop_pose`):
    boxes, then doors (`scene.slots.moving`), each at its scene pose where the record has none."""
    props = [moving(s.props) for s in scenes]
    nfree = max((sum(p.free for p in m) for m in props), default=0)
    ndoors = max((len(m) - sum(p.free for p in m) for m in props), default=0)
    out = np.zeros((int(length.sum()), nfree + ndoors, 7), dtype=dtype)
    out[..., 3] = 1.0
    row = 0
    for these, pose, n in zip(props, poses, length):
        boxes = [p for p in these if p.free]
        for k, prop in enumerate(these):
            slot = k if prop.free else nfree + k - len(boxes)
            out[row:row + n, slot] = pose[prop.name] if prop.name in pose else _rest_pose(prop)
        row += n
    return out


def _rest_pose(prop) -> np.ndarray:
    """A moving prop's scene pose: a box's centre and orientation, a door's closed hinge frame."""
    if prop.free:
        (g,) = prop.geoms()
        return np.r_[g.centre, g.quat]
    return prop.pose(0.0)
