"""The props of a batched scene: slots for every prop set of a simulator, filled per world.

`mujoco.rollout` steps all worlds with one MjModel structure, so a simulator whose worlds have
different props holds slots for the union of them, as `ground.TerrainScene` does for terrains:

- fixed props (shelves, desks): box geoms of the world body, `props_fixed_K`, as many as the prop
  set with the most fixed geoms has; a world poses and sizes them as its set's geoms, in order, and
  makes the rest inert and invisible;
- free props (boxes): bodies with a free joint and one box geom, `props_free_K`, as many as the set
  with the most boxes has; a world gives each the size, mass, inertia and friction of its set's
  box, in order. An unused free slot is parked: no collisions, invisible, its weight cancelled by
  MuJoCo's gravity compensation (`body_gravcomp`), so at rest it stays exactly put.

The slots come after the robot in the tree: the robot's qpos and qvel stay first, then each free
slot's 7 positions and 6 velocities. A prop set of a world is an index (`WorldParams.props`).
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from opt2skill.errors import ConfigError
from opt2skill.model.mujoco_model import GROUND_CONAFFINITY, GROUND_CONTYPE
from opt2skill.scene.build import PROP_PRIORITY, PROP_RGBA
from opt2skill.scene.ground import place_box, refit_tree
from opt2skill.scene.props import Box, Desk, Prop, Shelf

FIXED, FREE = "props_fixed_{}", "props_free_{}"
PARKED = np.array([0.0, 0.0, -10.0, 1.0, 0.0, 0.0, 0.0])  # an unused free slot, below the ground


class PropSlots:
    def __init__(self, prop_sets: Sequence[Sequence[Prop]] = ((),)):
        self.sets = tuple(tuple(s) for s in prop_sets) or ((),)
        for props in self.sets:
            for p in props:
                if not isinstance(p, (Box, Shelf, Desk)):
                    kind = getattr(p, "kind", type(p).__name__)
                    raise ConfigError(f"the batched simulator cannot hold a {kind} (prop {getattr(p, 'name', p)!r}) yet; "
                                      f"its props are boxes, shelves and desks")
        self.nfixed = max(sum(len(p.geoms()) for p in s if p.fixed) for s in self.sets)
        self.nfree = max(len(self.free(i)) for i in range(len(self.sets)))

    def __bool__(self) -> bool:
        return bool(self.nfixed or self.nfree)

    def free(self, index: int) -> list[Box]:
        """The free props (boxes) of set `index`, in slot order."""
        return [p for p in self.sets[index] if p.free]

    def used(self, index: int) -> np.ndarray:
        """(nfree,) bool: which free slots set `index` fills."""
        return np.arange(self.nfree) < len(self.free(index))

    def rest_poses(self, index: int) -> np.ndarray:
        """(nfree, 7) the boxes of set `index` at their scene poses, unused slots parked."""
        out = np.tile(PARKED, (self.nfree, 1))
        for k, box in enumerate(self.free(index)):
            (g,) = box.geoms()
            out[k] = np.r_[g.centre, g.quat]
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

    def bind(self, model: mujoco.MjModel, nq_robot: int) -> None:
        """Find the slots in a model compiled from a spec they were added to."""
        def gid(name):
            return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)

        self._fixed = [gid(FIXED.format(k)) for k in range(self.nfixed)]
        self._free_geom = [gid(FREE.format(k)) for k in range(self.nfree)]
        self._free_body = [int(model.geom_bodyid[g]) for g in self._free_geom]
        joints = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{FREE.format(k)}/free") for k in range(self.nfree)]
        if min([*self._fixed, *self._free_geom, *joints], default=0) < 0:
            raise ConfigError("the model was not built with these prop slots")
        if any(int(model.jnt_qposadr[j]) != nq_robot + 7 * k for k, j in enumerate(joints)):
            raise ConfigError("the prop slots' free joints must follow the robot's joints in qpos")

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
