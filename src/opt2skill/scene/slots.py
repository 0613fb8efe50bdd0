"""The props of a batched scene: slots for every prop set of a simulator, filled per world.

`mujoco.rollout` steps all worlds with one MjModel structure, so a simulator whose worlds have
different props holds slots for the union of them, as `ground.TerrainScene` does for terrains:

- fixed props (shelves, desks): box geoms of the world body, `props_fixed_K`, as many as the prop
  set with the most fixed geoms has; a world poses and sizes them as its set's geoms, in order, and
  makes the rest inert and invisible;
- free props (boxes): bodies with a free joint and one box geom, `props_free_K`, as many as the set
  with the most boxes has; a world gives each the size, mass, inertia and friction of its set's
  box, in order. An unused free slot is parked: no collisions, invisible, its weight cancelled by
  MuJoCo's gravity compensation (`body_gravcomp`), so at rest it stays exactly put;
- doors: bodies on a hinge joint about z with one panel geom, `props_hinged_K`, as many as the set
  with the most doors has; a world puts each at its door's hinge and gives it the door's panel,
  mass, inertia, spring, damper, stop and friction. An unused one is hidden, without collisions.

The slots come after the robot in the tree: the robot's qpos and qvel stay first, then each free
slot's 7 positions and 6 velocities, then each door's angle and rate. A prop set of a world is an
index (`WorldParams.props`). The props that move (boxes, then doors: `moving`) have a pose each in
the simulator's outputs and resets, a door's being its hinge frame's (`Door.pose`).
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from opt2skill.errors import ConfigError
from opt2skill.model.mujoco_model import GROUND_CONAFFINITY, GROUND_CONTYPE
from opt2skill.scene.build import PROP_PRIORITY, PROP_RGBA
from opt2skill.scene.ground import place_box, refit_tree
from opt2skill.scene.props import Box, Desk, Door, Prop, Shelf

FIXED, FREE, HINGED = "props_fixed_{}", "props_free_{}", "props_hinged_{}"
PARKED = np.array([0.0, 0.0, -10.0, 1.0, 0.0, 0.0, 0.0])  # an unused free slot, below the ground


def moving(props: Sequence[Prop]) -> list[Box | Door]:
    """The props of a set that move, in slot order: its boxes, then its doors."""
    return [p for p in props if p.free] + [p for p in props if isinstance(p, Door)]


class PropSlots:
    def __init__(self, prop_sets: Sequence[Sequence[Prop]] = ((),)):
        self.sets = tuple(tuple(s) for s in prop_sets) or ((),)
        for props in self.sets:
            for p in props:
                if not isinstance(p, (Box, Shelf, Desk, Door)):
                    raise ConfigError(f"unknown prop {p!r}; props are Box, Shelf, Desk and Door")
        self.nfixed = max(sum(len(p.geoms()) for p in s if p.fixed) for s in self.sets)
        self.nfree = max(len(self.free(i)) for i in range(len(self.sets)))
        self.nhinged = max(len(self.doors(i)) for i in range(len(self.sets)))
        self.nmoving = self.nfree + self.nhinged  # poses in the outputs: boxes' slots, then doors'

    def __bool__(self) -> bool:
        return bool(self.nfixed or self.nmoving)

    def free(self, index: int) -> list[Box]:
        """The free props (boxes) of set `index`, in slot order."""
        return [p for p in self.sets[index] if p.free]

    def doors(self, index: int) -> list[Door]:
        return [p for p in self.sets[index] if isinstance(p, Door)]

    def used(self, index: int) -> np.ndarray:
        """(nmoving,) bool: which free slots, then which door slots, set `index` fills."""
        return np.r_[np.arange(self.nfree) < len(self.free(index)), np.arange(self.nhinged) < len(self.doors(index))]

    def rest_poses(self, index: int) -> np.ndarray:
        """(nmoving, 7) the boxes of set `index` at their scene poses, unused slots parked, then its
        doors closed (unused: the identity at the origin)."""
        out = np.tile(PARKED, (self.nmoving, 1))
        for k, box in enumerate(self.free(index)):
            (g,) = box.geoms()
            out[k] = np.r_[g.centre, g.quat]
        out[self.nfree:] = [1.0 if i == 3 else 0.0 for i in range(7)]
        for k, door in enumerate(self.doors(index)):
            out[self.nfree + k] = door.pose(0.0)
        return out

    def door_angles(self, index: int, poses: np.ndarray) -> np.ndarray:
        """(..., nhinged) the hinge angles of set `index`'s doors in poses (..., nhinged, 7); 0 in unused slots."""
        out = np.zeros(poses.shape[:-1])
        for k, door in enumerate(self.doors(index)):
            out[..., k] = door.angle_of(poses[..., k, :])
        return out

    def door_poses(self, index: int, angles: np.ndarray) -> np.ndarray:
        """(..., nhinged, 7) the hinge frames of set `index`'s doors at angles (..., nhinged)."""
        out = np.zeros((*angles.shape, 7))
        out[..., 3] = 1.0
        for k, door in enumerate(self.doors(index)):
            out[..., k, :] = door.pose(angles[..., k])
        return out

    def add_to(self, spec: mujoco.MjSpec) -> None:
        """Add the slots to a scene spec (after the robot, so its qpos and qvel stay first)."""
        # Compiled able to collide (MuJoCo refuses to turn on collisions a geom was compiled without);
        # `apply` then shows or hides each slot.
        box = dict(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.1, 0.1, 0.1], contype=GROUND_CONTYPE,
                   conaffinity=GROUND_CONAFFINITY, rgba=[0.0, 0.0, 0.0, 0.0], priority=PROP_PRIORITY)
        for k in range(self.nfixed):
            spec.worldbody.add_geom(name=FIXED.format(k), **box)
        for k in range(self.nfree):
            # gravcomp at compile time: MuJoCo skips gravity compensation in a model without any.
            body = spec.worldbody.add_body(name=FREE.format(k), pos=PARKED[:3], mass=1.0, ipos=[0.0, 0.0, 0.0],
                                           inertia=[0.01, 0.01, 0.01], explicitinertial=True, gravcomp=1.0)
            body.add_freejoint(name=f"{FREE.format(k)}/free")
            body.add_geom(name=FREE.format(k), **box)
        for k in range(self.nhinged):
            body = spec.worldbody.add_body(name=HINGED.format(k), mass=1.0, ipos=[0.0, 0.0, 0.0],
                                           inertia=[0.01, 0.01, 0.01], explicitinertial=True)
            body.add_joint(name=f"{HINGED.format(k)}/hinge", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0.0, 0.0, 1.0],
                           limited=mujoco.mjtLimited.mjLIMITED_TRUE, range=[0.0, 1.0])
            body.add_geom(name=HINGED.format(k), **box)

    def bind(self, model: mujoco.MjModel, nq_robot: int) -> None:
        """Find the slots in a model compiled from a spec they were added to."""
        def gid(name):
            return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)

        self._fixed = [gid(FIXED.format(k)) for k in range(self.nfixed)]
        self._free_geom = [gid(FREE.format(k)) for k in range(self.nfree)]
        self._free_body = [int(model.geom_bodyid[g]) for g in self._free_geom]
        joints = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{FREE.format(k)}/free") for k in range(self.nfree)]
        self._hinged_geom = [gid(HINGED.format(k)) for k in range(self.nhinged)]
        self._hinged_body = [int(model.geom_bodyid[g]) for g in self._hinged_geom]
        self._hinges = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{HINGED.format(k)}/hinge")
                        for k in range(self.nhinged)]
        if min([*self._fixed, *self._free_geom, *joints, *self._hinged_geom, *self._hinges], default=0) < 0:
            raise ConfigError("the model was not built with these prop slots")
        if any(int(model.jnt_qposadr[j]) != nq_robot + 7 * k for k, j in enumerate(joints)):
            raise ConfigError("the prop slots' free joints must follow the robot's joints in qpos")
        if any(int(model.jnt_qposadr[j]) != nq_robot + 7 * self.nfree + k for k, j in enumerate(self._hinges)):
            raise ConfigError("the door slots' hinges must follow the free slots in qpos")
        for body in self._hinged_body:  # compiled with the inertia at the hinge; a door's is at its panel's centre
            model.body_simple[body] = 0
            model.body_sameframe[body] = mujoco.mjtSameFrame.mjSAMEFRAME_NONE

    def apply(self, model: mujoco.MjModel, index: int, friction_scale: float = 1.0) -> None:
        """Make `model` show prop set `index` (its fixed props posed, its boxes sized and weighed) and
        nothing else of the slots; friction is the props' own times `friction_scale`. Masses and
        inertias change: call `mj_setConst` afterwards."""
        fixed = [g for p in self.sets[index] if p.fixed for g in p.geoms()]
        fixed_props = [p for p in self.sets[index] if p.fixed for _ in p.geoms()]
        for k, gid in enumerate(self._fixed):
            if k < len(fixed):
                g = fixed[k]
                place_box(model, gid, g.centre, g.half, g.quat)
                self._show(model, gid, fixed_props[k], friction_scale)
            else:
                self._hide(model, gid)
        if self.nfixed:
            refit_tree(model)
        boxes = self.free(index)
        for k, (gid, body) in enumerate(zip(self._free_geom, self._free_body)):
            if k < len(boxes):
                box = boxes[k]
                place_box(model, gid, np.zeros(3), np.array(box.size) / 2)
                model.body_mass[body] = box.mass
                model.body_inertia[body] = box.inertia
                model.body_gravcomp[body] = 0.0
                self._show(model, gid, box, friction_scale)
            else:
                model.body_gravcomp[body] = 1.0
                self._hide(model, gid)
            refit_tree(model, body)
        doors = self.doors(index)
        for k, (gid, body, joint) in enumerate(zip(self._hinged_geom, self._hinged_body, self._hinges)):
            dof = model.jnt_dofadr[joint]
            if k < len(doors):
                door = doors[k]
                (g,) = door.geoms()
                model.body_pos[body], model.body_quat[body] = [*door.hinge, 0.0], door.pose(0.0)[3:]
                place_box(model, gid, door.panel_centre, g.half)
                model.body_mass[body], model.body_inertia[body] = door.mass, door.inertia
                model.body_ipos[body] = door.panel_centre
                model.jnt_stiffness[joint], model.dof_damping[dof] = door.stiffness, door.damping
                model.jnt_range[joint] = [0.0, door.max_angle]
                self._show(model, gid, door, friction_scale)
            else:
                model.jnt_stiffness[joint] = model.dof_damping[dof] = 0.0
                self._hide(model, gid)
            refit_tree(model, body)

    @staticmethod
    def _show(model: mujoco.MjModel, gid: int, prop: Prop, friction_scale: float) -> None:
        model.geom_contype[gid], model.geom_conaffinity[gid] = GROUND_CONTYPE, GROUND_CONAFFINITY
        condim, friction = prop.contact  # as `build.add_prop` gives it
        model.geom_condim[gid] = condim
        model.geom_friction[gid] = np.array(friction) * friction_scale
        model.geom_rgba[gid] = PROP_RGBA[prop.kind]

    @staticmethod
    def _hide(model: mujoco.MjModel, gid: int) -> None:
        model.geom_contype[gid] = model.geom_conaffinity[gid] = 0
        model.geom_rgba[gid] = 0.0
