"""The ground of a batched scene: one set of geoms able to show every terrain of a simulator, and
the switch that makes a world's MjModel copy show one of them.

The scene holds the plane, one heightfield geom (if any terrain is rough), as many step boxes as
the longest stairs need, and an incline box plus a landing box (if any terrain is a slope). A world
shows its terrain by giving those geoms their collision bits and making the rest inert and
invisible; heightfield data, box sizes, positions and orientations are per MjModel, so every world
can differ. Box bounding volumes, the world body's bounding-volume tree and the boxes' frame flags
are updated with the boxes, because collision culling and kinematics use them.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from opt2skill.errors import ConfigError
from opt2skill.model.mujoco_model import FLOOR_FRICTION, GROUND_CONAFFINITY, GROUND_CONTYPE
from opt2skill.scene.terrain import Flat, Rough, Slope, Stairs, Terrain

FLOOR, HFIELD, INCLINE, TOP = "floor", "terrain_hfield", "slope_incline", "slope_top"
GROUND_RGBA = [0.45, 0.42, 0.38, 1.0]
HFIELD_BASE = 0.1  # thickness of the heightfield's solid base below its lowest point, m


class TerrainScene:
    def __init__(self, terrains: Sequence[Terrain]):
        self.terrains = tuple(terrains)
        if not self.terrains:
            raise ConfigError("a simulator needs at least one terrain (e.g. terrain.flat())")
        for t in self.terrains:
            if not isinstance(t, (Flat, Rough, Stairs, Slope)):
                raise ConfigError(f"unknown terrain {t!r}; terrains are Flat, Rough, Stairs and Slope")
        grids = {t.grid for t in self.terrains if isinstance(t, Rough)}
        if len(grids) > 1:
            raise ConfigError("all rough terrains of a simulator must share one TerrainGrid")
        self.grid = grids.pop() if grids else None
        self.nstep_boxes = max((t.n_steps for t in self.terrains if isinstance(t, Stairs)), default=0)
        self.has_slope = any(isinstance(t, Slope) for t in self.terrains)
        self._normalized = {
            i: ((t.heights - self.grid.z_range[0]) / np.diff(self.grid.z_range)[0]).astype(np.float32).ravel()
            for i, t in enumerate(self.terrains) if isinstance(t, Rough)
        }
        self._ids: dict[str, int] = {}

    def add_to(self, spec: mujoco.MjSpec) -> None:
        """Add the ground geoms (besides the robot's plane, named 'floor') to a scene spec."""
        ground = dict(contype=GROUND_CONTYPE, conaffinity=GROUND_CONAFFINITY, friction=list(FLOOR_FRICTION),
                      rgba=GROUND_RGBA)
        if self.grid is not None:
            g = self.grid
            size = [np.diff(g.x_range)[0] / 2, np.diff(g.y_range)[0] / 2, np.diff(g.z_range)[0], HFIELD_BASE]
            spec.add_hfield(name=HFIELD, nrow=g.nrow, ncol=g.ncol, size=size, userdata=[0.0] * (g.nrow * g.ncol))
            centre = [np.mean(g.x_range), np.mean(g.y_range), g.z_range[0]]
            spec.worldbody.add_geom(name=HFIELD, type=mujoco.mjtGeom.mjGEOM_HFIELD, hfieldname=HFIELD, pos=centre,
                                    **ground)
        boxes = [f"step_{k}" for k in range(self.nstep_boxes)] + ([INCLINE, TOP] if self.has_slope else [])
        for name in boxes:
            spec.worldbody.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.5, 0.5, 0.5], **ground)

    def bind(self, model: mujoco.MjModel) -> None:
        """Find the ground geoms in a model compiled from a spec this scene was added to."""
        names = [FLOOR, HFIELD, INCLINE, TOP] + [f"step_{k}" for k in range(self.nstep_boxes)]
        self._ids = {n: i for n in names if (i := mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n)) >= 0}
        if FLOOR not in self._ids:
            raise ConfigError("the robot scene has no geom named 'floor'")
        self._look = {gid: (int(model.geom_matid[gid]), model.geom_rgba[gid].copy()) for gid in self._ids.values()}
        self._boxes = {name for name in self._ids if name not in (FLOOR, HFIELD)}

    def apply(self, model: mujoco.MjModel, index: int) -> None:
        """Make `model` show terrain `index` and nothing else of the ground."""
        terrain = self.terrains[index]
        shown: set[str] = set()
        if isinstance(terrain, Rough):
            model.hfield_data[:] = self._normalized[index]
            shown.add(HFIELD)
        else:
            shown.add(FLOOR)
        if isinstance(terrain, Stairs) and terrain.step_height > 0:
            for k, (centre, half) in enumerate(terrain.boxes()):
                self._place_box(model, f"step_{k}", centre, half)
                shown.add(f"step_{k}")
        if isinstance(terrain, Slope) and terrain.angle_deg > 0:
            centre, half, quat = terrain.incline()
            self._place_box(model, INCLINE, centre, half, quat)
            self._place_box(model, TOP, *terrain.top())
            shown |= {INCLINE, TOP}
        if shown & self._boxes:
            refit_tree(model)
        for name, gid in self._ids.items():
            active = name in shown
            model.geom_contype[gid] = GROUND_CONTYPE if active else 0
            model.geom_conaffinity[gid] = GROUND_CONAFFINITY if active else 0
            # Hidden from rendering and rays too: no material and a transparent colour.
            matid, rgba = self._look[gid]
            model.geom_matid[gid] = matid if active else -1
            model.geom_rgba[gid] = rgba if active else 0.0

    def _place_box(self, model, name, centre, half, quat=(1.0, 0.0, 0.0, 0.0)) -> None:
        place_box(model, self._ids[name], centre, half, quat)


def place_box(model: mujoco.MjModel, gid: int, centre, half, quat=(1.0, 0.0, 0.0, 0.0)) -> None:
    """Pose and size box geom `gid` in its body's frame, with the bounds collision culling uses."""
    model.geom_pos[gid] = centre
    model.geom_quat[gid] = quat
    model.geom_size[gid] = half
    model.geom_aabb[gid] = np.r_[0.0, 0.0, 0.0, half]
    model.geom_rbound[gid] = np.linalg.norm(half)
    # Compiled at the origin, the box was marked as sharing its body's frame, which would make
    # MuJoCo ignore geom_pos and geom_quat.
    model.geom_sameframe[gid] = mujoco.mjtSameFrame.mjSAMEFRAME_NONE


def refit_tree(model: mujoco.MjModel, body: int = 0) -> None:
    """Recompute a body's (the world's by default) bounding-volume tree from its geoms' current
    poses and boxes.

    MuJoCo builds the tree at compile time; its midphase prunes geom pairs with it, so boxes moved
    afterwards need it refitted (same tree, new volumes: leaves bound their geom, parents their
    children; children come after their parent in the array).
    """
    adr, num = model.body_bvhadr[body], model.body_bvhnum[body]
    aabb, rot = model.bvh_aabb[adr:adr + num], np.zeros(9)
    for node in range(num - 1, -1, -1):
        geom = model.bvh_nodeid[adr + node]
        if geom >= 0:
            mujoco.mju_quat2Mat(rot, model.geom_quat[geom])
            r = rot.reshape(3, 3)
            aabb[node] = np.r_[model.geom_pos[geom] + r @ model.geom_aabb[geom, :3], np.abs(r) @ model.geom_aabb[geom, 3:]]
        else:
            a, b = model.bvh_child[adr + node]
            lo = np.minimum(aabb[a, :3] - aabb[a, 3:], aabb[b, :3] - aabb[b, 3:])
            hi = np.maximum(aabb[a, :3] + aabb[a, 3:], aabb[b, :3] + aabb[b, 3:])
            # Slack for rounding: next to the plane's 1e10 bounds, centre + half is off by micrometres.
            slack = 4 * np.finfo(float).eps * np.maximum(np.abs(lo), np.abs(hi))
            aabb[node] = np.r_[(lo + hi) / 2, (hi - lo) / 2 + slack]
