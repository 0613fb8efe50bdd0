"""Offscreen videos of a motion, optionally with a translucent reference "ghost" beside it.

Rendering needs no display: on Linux without one, opt2skill selects MuJoCo's EGL backend
(`MUJOCO_GL=egl`, set in `opt2skill/__init__.py` unless the user chose another). Frames are
written to MP4 (H.264) with imageio's ffmpeg.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import imageio
import mujoco
import numpy as np

from opt2skill.data.record import FRAME_DT
from opt2skill.errors import ConfigError
from opt2skill.model.mujoco_model import load_spec
from opt2skill.model.robot import Robot
from opt2skill.scene.build import add_scene, prop_hinge, prop_qpos, show_ground
from opt2skill.scene.description import Scene
from opt2skill.scene.ground import TerrainScene
from opt2skill.scene.props import Door
from opt2skill.scene.terrain import Terrain

GHOST_RGBA = (0.2, 0.7, 1.0, 0.3)
GHOST_PREFIX = "ghost/"


def scene_model(robot: Robot, ghost: bool, add_terrain: Callable[[mujoco.MjSpec], None] | None = None,
                terrain: Terrain | None = None, scene: Scene | None = None) -> mujoco.MjModel:
    """The robot on its floor (or on a terrain added by `add_terrain`, or on one of the simulator's
    terrains: stairs, slopes, rough ground, or in a record's `scene` with its props), plus a
    non-colliding ghost (its qpos at `ghost_qpos_address`)."""
    if sum(x is not None for x in (add_terrain, terrain, scene)) > 1:
        raise ConfigError("render on one ground: give add_terrain, terrain or scene, not several")
    spec = robot.mj_spec(floor=add_terrain is None)
    if add_terrain is not None:
        add_terrain(spec)
    ground = None
    if terrain is not None:
        ground = TerrainScene([terrain])
        ground.add_to(spec)
    elif scene is not None:
        ground = add_scene(spec, scene)
    if ghost:
        copy = load_spec(robot.config)
        for geom in copy.geoms:
            geom.contype, geom.conaffinity, geom.rgba = 0, 0, list(GHOST_RGBA)
            geom.material = ""
        spec.attach(copy, prefix=GHOST_PREFIX, frame=spec.worldbody.add_frame())
    spec.visual.headlight.ambient = [0.45, 0.45, 0.45]
    spec.visual.headlight.diffuse = [0.6, 0.6, 0.6]
    model = robot.compile(spec)
    if ground is not None:
        show_ground(model, ground)
    return model


def ghost_qpos_address(model: mujoco.MjModel, robot: Robot) -> int:
    """Where the ghost's qpos starts (after the robot's and any prop's)."""
    joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, GHOST_PREFIX + robot.config.root_joint)
    if joint < 0:
        raise ConfigError("the model has no ghost")
    return int(model.jnt_qposadr[joint])


def render_video(
    robot: Robot,
    qpos: np.ndarray,
    out: str | Path,
    ghost_qpos: np.ndarray | None = None,
    fps: int = 30,
    size: tuple[int, int] = (480, 640),
    frame_dt: float = FRAME_DT,
    add_terrain: Callable[[mujoco.MjSpec], None] | None = None,
    terrain: Terrain | None = None,
    scene: Scene | None = None,
    prop_poses: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write `qpos` (T, nq) frames, `frame_dt` apart, as a video; the ghost shows `ghost_qpos`.
    The scene's moving props are at `prop_poses` (a record's: name -> (T, 7)) where given, else at
    their scene poses.

    The camera looks at the robot's base from behind and to the side and follows it smoothly.
    """
    qpos = np.asarray(qpos, dtype=float)
    if qpos.ndim != 2 or qpos.shape[1] != robot.nq or len(qpos) < 2:
        raise ConfigError(f"qpos must have shape (T >= 2, {robot.nq}), got {qpos.shape}")
    if ghost_qpos is not None and np.shape(ghost_qpos)[1:] != (robot.nq,):
        raise ConfigError(f"ghost qpos must have shape (T, {robot.nq}), got {np.shape(ghost_qpos)}")
    if not 1 <= fps <= 240:
        raise ConfigError(f"fps must be in [1, 240], got {fps}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    model = scene_model(robot, ghost=ghost_qpos is not None, add_terrain=add_terrain, terrain=terrain, scene=scene)
    data = mujoco.MjData(model)  # props at their scene poses, unless posed below
    place = _prop_placer(model, scene, prop_poses or {})
    ghost_at = ghost_qpos_address(model, robot) if ghost_qpos is not None else 0
    times = np.arange(0.0, (len(qpos) - 1) * frame_dt + 1e-9, 1.0 / fps)
    frames = np.minimum(np.rint(times / frame_dt).astype(int), len(qpos) - 1)
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.distance, camera.azimuth, camera.elevation = 3.5, 150.0, -15.0
    lookat = np.array([*qpos[0, :2], 0.75])
    tmp = out.with_name(out.name + ".tmp.mp4")
    with mujoco.Renderer(model, *size) as renderer, imageio.get_writer(tmp, fps=fps, codec="libx264", macro_block_size=8) as writer:
        for f in frames:
            data.qpos[: robot.nq] = qpos[f]
            place(data, f)
            if ghost_qpos is not None:
                data.qpos[ghost_at : ghost_at + robot.nq] = ghost_qpos[min(f, len(ghost_qpos) - 1)]
            mujoco.mj_kinematics(model, data)
            lookat[:2] += 0.2 * (qpos[f, :2] - lookat[:2])  # smooth follow, no jitter at each step
            camera.lookat[:] = lookat
            renderer.update_scene(data, camera)
            writer.append_data(renderer.render())
    tmp.replace(out)
    return out


def _prop_placer(model: mujoco.MjModel, scene: Scene | None, poses: dict[str, np.ndarray]):
    """(data, frame) -> None: puts each posed prop of the scene where its poses say at that frame
    (a box's free joint, a door's hinge angle)."""
    slots = []
    for prop in scene.props if scene is not None else ():
        if prop.name not in poses:
            continue
        pose = np.asarray(poses[prop.name], dtype=float)
        if isinstance(prop, Door):
            at = prop_hinge(model, prop.name)
            slots.append((slice(at, at + 1), prop.angle_of(pose)[:, None]))
        elif prop.free:
            slots.append((prop_qpos(model, prop.name), pose))

    def place(data: mujoco.MjData, frame: int) -> None:
        for at, values in slots:
            data.qpos[at] = values[min(frame, len(values) - 1)]

    return place
