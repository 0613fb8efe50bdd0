"""A scene in MuJoCo: the robot, its ground and its props in one model.

`build_model(robot, scene)` is the one way a scene becomes an MjModel. The ground is a
`TerrainScene` of the scene's single terrain (the same geoms and placement the batched simulator
uses); fixed props are boxes of the world body; a `Box` prop is a body with a free joint and the
given mass; a `Door` a body on a hinge joint whose spring (`stiffness`, `springref` 0) and `damping`
close it, a stop at 0 and at its `max_angle`. Props come after the robot in the tree, so the robot's
qpos, qvel, controls and sensors keep their places at the front and a prop's free joint follows
(`prop_qpos`), or its hinge (`prop_hinge`).
"""

from __future__ import annotations

from collections.abc import Collection

import mujoco

from opt2skill.model.mujoco_model import GROUND_CONAFFINITY, GROUND_CONTYPE
from opt2skill.model.robot import Robot
from opt2skill.scene.description import Scene
from opt2skill.scene.ground import TerrainScene
from opt2skill.scene.props import Door, Prop

PROP_PRIORITY = 1  # above the robot's geoms (0): contacts with a prop use the prop's own friction
PROP_RGBA = {"box": [0.75, 0.55, 0.3, 1.0], "shelf": [0.55, 0.45, 0.35, 1.0], "desk": [0.6, 0.5, 0.4, 1.0],
             "door": [0.5, 0.35, 0.25, 1.0]}


def build_model(robot: Robot, scene: Scene, sensors: Collection[str] | None = None) -> mujoco.MjModel:
    """The robot standing in `scene`: floor or terrain, props, PD actuators and sensors (only those
    named in `sensors` when given: a model stepped for a few of them skips the cost of the rest)."""
    spec = robot.mj_spec()
    if sensors is not None:
        unknown = set(sensors) - {s.name for s in spec.sensors}
        if unknown:
            raise KeyError(f"robot '{robot.name}' has no sensor {', '.join(sorted(unknown))}")
        for sensor in [s for s in spec.sensors if s.name not in sensors]:
            spec.delete(sensor)
    ground = add_scene(spec, scene)
    model = robot.compile(spec)
    show_ground(model, ground)
    return model


def add_scene(spec: mujoco.MjSpec, scene: Scene) -> TerrainScene:
    """Add the scene's ground geoms and props to a robot spec (with its floor). Compile it, then
    call `show_ground` with the returned ground."""
    ground = TerrainScene([scene.ground])
    ground.add_to(spec)
    for prop in scene.props:
        add_prop(spec, prop)
    return ground


def show_ground(model: mujoco.MjModel, ground: TerrainScene) -> None:
    """Place and enable the ground geoms in a model compiled from a spec `add_scene` filled."""
    ground.bind(model)
    ground.apply(model, 0)


def add_prop(spec: mujoco.MjSpec, prop: Prop) -> None:
    """A fixed prop's geoms on the world body, or a box on its own free body. MuJoCo names are
    `NAME/GEOM` (fixed) and the body `NAME` with joint `NAME/free` (free)."""
    # PROP_PRIORITY: a contact with a prop has the prop's friction (MuJoCo otherwise takes the larger
    # of the two geoms', and the robot's geoms have 1), so a whiteboard is slippery under a hand.
    condim, friction = prop.contact
    look = dict(type=mujoco.mjtGeom.mjGEOM_BOX, contype=GROUND_CONTYPE, conaffinity=GROUND_CONAFFINITY,
                condim=condim, friction=list(friction), rgba=PROP_RGBA[prop.kind], priority=PROP_PRIORITY)
    if prop.fixed:
        for g in prop.geoms():
            spec.worldbody.add_geom(name=f"{prop.name}/{g.name}", size=g.half, pos=g.centre, quat=g.quat, **look)
        return
    if isinstance(prop, Door):
        add_door(spec, prop, look)
        return
    (g,) = prop.geoms()
    # The robot's MJCF compiles with inertiafromgeom="false": the box's inertia is given, uniform.
    # ipos must be set: unset (NaN) it compiles to the body's own position, off the centre.
    body = spec.worldbody.add_body(name=prop.name, pos=g.centre, quat=g.quat, mass=prop.mass, ipos=[0.0, 0.0, 0.0],
                                   inertia=prop.inertia, explicitinertial=True)
    body.add_freejoint(name=f"{prop.name}/free")
    body.add_geom(name=prop.name, size=g.half, **look)


def add_door(spec: mujoco.MjSpec, door: Door, look: dict) -> None:
    """The door: body `NAME` at the hinge (turned by its yaw), hinge joint `NAME/hinge` about z, the
    panel geom `NAME` with its uniform inertia about its centre."""
    body = spec.worldbody.add_body(name=door.name, pos=[*door.hinge, 0.0], quat=door.pose(0.0)[3:], mass=door.mass,
                                   ipos=door.panel_centre, inertia=door.inertia, explicitinertial=True)
    body.add_joint(name=f"{door.name}/hinge", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0.0, 0.0, 1.0],
                   stiffness=door.stiffness, damping=door.damping, springref=0.0, limited=mujoco.mjtLimited.mjLIMITED_TRUE,
                   range=[0.0, door.max_angle])
    (g,) = door.geoms()
    body.add_geom(name=door.name, size=g.half, pos=door.panel_centre, **look)


def prop_hinge(model: mujoco.MjModel, name: str) -> int:
    """Where a door's hinge angle sits in qpos."""
    jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{name}/hinge")
    if jid < 0:
        raise KeyError(f"the model has no door '{name}'")
    return int(model.jnt_qposadr[jid])


def prop_qpos(model: mujoco.MjModel, name: str) -> slice:
    """Where a free prop's position and quaternion (w, x, y, z) sit in qpos."""
    jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{name}/free")
    if jid < 0:
        raise KeyError(f"the model has no free prop '{name}'")
    adr = int(model.jnt_qposadr[jid])
    return slice(adr, adr + 7)
