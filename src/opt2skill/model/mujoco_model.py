"""The robot in MuJoCo: its MJCF plus a scene, PD actuators and sensors, all from the robot config.

The MJCF holds the robot only. Gains and torque limits live in robot.yaml, so this module adds the
position servos (u = kp (ctrl - q) - kd qdot, clipped to the torque limit) and the sensors a
tracking policy reads. Sensor names are part of the interface that `sim` reads; see docs/model.md.
"""

from __future__ import annotations

import mujoco
import numpy as np

from opt2skill.errors import ModelError
from opt2skill.robots import RobotConfig

FLOOR_FRICTION = (1.0, 0.005, 0.0001)  # MuJoCo's default sliding, torsional, rolling coefficients
# Collision bits (docs/robots.md): feet 1/1, other robot geoms 0/2, ground and objects hit both.
GROUND_CONTYPE = 3
GROUND_CONAFFINITY = 1


def load_spec(config: RobotConfig) -> mujoco.MjSpec:
    """The robot's MJCF as an editable spec, with its joints checked against the config."""
    try:
        spec = mujoco.MjSpec.from_file(str(config.mjcf_path))
    except Exception as exc:  # MuJoCo raises ValueError with its parser message
        raise ModelError(f"cannot read MJCF {config.mjcf_path}: {_first_line(exc)}") from None
    joints = list(spec.joints)
    if not joints or joints[0].type != mujoco.mjtJoint.mjJNT_FREE or joints[0].name != config.root_joint:
        raise ModelError(
            f"{config.mjcf_path}: the first joint must be a free joint named '{config.root_joint}' "
            "(the floating base)"
        )
    hinge_names = [j.name for j in joints[1:]]
    _check_joint_order(config, hinge_names, str(config.mjcf_path))
    bad = [j.name for j in joints[1:] if j.type != mujoco.mjtJoint.mjJNT_HINGE]
    if bad:
        raise ModelError(f"{config.mjcf_path}: actuated joints must be hinges; not hinges: {bad}")
    _check_names(spec, config)
    return spec


def build_spec(config: RobotConfig, floor: bool = True) -> mujoco.MjSpec:
    """Robot, optional flat floor, light, PD actuators and sensors. Callers may add terrain or objects."""
    spec = load_spec(config)
    world = spec.worldbody
    if floor:
        add_floor(spec)
    world.add_light(pos=[0, 0, 4], dir=[0, 0, -1], diffuse=[0.8, 0.8, 0.8], castshadow=False)
    _add_actuators(spec, config)
    _add_sensors(spec, config)
    return spec


def add_floor(spec: mujoco.MjSpec, size: float = 50.0) -> None:
    tex = spec.add_texture(
        name="grid", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        rgb1=[0.25, 0.3, 0.35], rgb2=[0.35, 0.4, 0.45], width=256, height=256,
    )
    mat = spec.add_material(name="grid", texrepeat=[1, 1], texuniform=True)
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = tex.name
    spec.worldbody.add_geom(
        name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[size, size, 0.1], material="grid",
        contype=GROUND_CONTYPE, conaffinity=GROUND_CONAFFINITY, friction=list(FLOOR_FRICTION),
    )


def compile_spec(spec: mujoco.MjSpec, where: str) -> mujoco.MjModel:
    try:
        return spec.compile()
    except Exception as exc:
        raise ModelError(f"MuJoCo cannot compile {where}: {_first_line(exc)}") from None


def _add_actuators(spec: mujoco.MjSpec, config: RobotConfig) -> None:
    for joint in config.joints:
        act = spec.add_actuator(name=joint.name, target=joint.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=joint.kp, kv=joint.kd)
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-joint.torque_limit, joint.torque_limit]


def _add_sensors(spec: mujoco.MjSpec, config: RobotConfig) -> None:
    site, joint_obj, act_obj = mujoco.mjtObj.mjOBJ_SITE, mujoco.mjtObj.mjOBJ_JOINT, mujoco.mjtObj.mjOBJ_ACTUATOR
    s = mujoco.mjtSensor
    imu = config.imu_site
    spec.add_sensor(name="imu_quat", type=s.mjSENS_FRAMEQUAT, objtype=site, objname=imu)
    spec.add_sensor(name="imu_gyro", type=s.mjSENS_GYRO, objtype=site, objname=imu)
    spec.add_sensor(name="imu_linvel", type=s.mjSENS_VELOCIMETER, objtype=site, objname=imu)
    spec.add_sensor(name="imu_acc", type=s.mjSENS_ACCELEROMETER, objtype=site, objname=imu)
    for joint in config.joint_names:
        spec.add_sensor(name=f"q_{joint}", type=s.mjSENS_JOINTPOS, objtype=joint_obj, objname=joint)
    for joint in config.joint_names:
        spec.add_sensor(name=f"qd_{joint}", type=s.mjSENS_JOINTVEL, objtype=joint_obj, objname=joint)
    for joint in config.joint_names:
        spec.add_sensor(name=f"tau_{joint}", type=s.mjSENS_ACTUATORFRC, objtype=act_obj, objname=joint)
    for name, site_name in config.end_effectors.items():
        spec.add_sensor(name=f"ee_{name}", type=s.mjSENS_FRAMEPOS, objtype=site, objname=site_name)
    for foot in config.feet:
        # Net contact wrench on the foot's subtree: found(1), force(3), torque(3), point(3), world axes.
        # MuJoCo reports the force the foot exerts on the ground; sim flips the sign (docs/model.md).
        spec.add_sensor(
            name=f"contact_{foot.name}", type=s.mjSENS_CONTACT, objtype=mujoco.mjtObj.mjOBJ_XBODY,
            objname=foot.body, intprm=[1 | 2 | 4 | 16, 3, 1],  # data: found|force|torque|pos; reduce: netforce
        )
    # Appended after the original sensors so their addresses stay put. The sole positions are the
    # points contact wrenches are taken about; the end-effector velocities and accelerations let
    # `sim` carry positions measured at the start of a physics step to its end (docs/sim.md).
    for foot in config.feet:
        spec.add_sensor(name=f"sole_{foot.name}", type=s.mjSENS_FRAMEPOS, objtype=site, objname=foot.sole_site)
    for name, site_name in config.end_effectors.items():
        spec.add_sensor(name=f"eevel_{name}", type=s.mjSENS_FRAMELINVEL, objtype=site, objname=site_name)
    for name, site_name in config.end_effectors.items():
        spec.add_sensor(name=f"eeacc_{name}", type=s.mjSENS_FRAMELINACC, objtype=site, objname=site_name)
    # Point contacts (hands, elbows: every end effector that is not a foot): the net contact force on
    # each collision geom at the end effector's site, summed per end effector by `SensorLayout`.
    for name, geoms in point_contact_geoms(spec, config).items():
        for k, geom in enumerate(geoms):
            spec.add_sensor(
                name=f"pcontact_{name}_{k}", type=s.mjSENS_CONTACT, objtype=mujoco.mjtObj.mjOBJ_GEOM,
                objname=geom, intprm=[1 | 2, 3, 1],  # data: found|force; reduce: netforce (3), one
            )


def point_contact_geoms(spec: mujoco.MjSpec, config: RobotConfig) -> dict[str, tuple[str, ...]]:
    """The robot's collision geoms whose volume holds each point-contact end effector's site, at the
    model's reference pose: the hand's sphere for a hand; for an elbow (a site on the joint axis) the
    links on both sides of the joint. Contacts on these geoms are that end effector's contacts."""
    feet = {f.name for f in config.feet}
    points = {name: site for name, site in config.end_effectors.items() if name not in feet}
    if not points:
        return {}
    model = spec.copy().compile()  # the robot as built so far (no sensors needed for geometry)
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    robot_geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] != 0
                   and (model.geom_contype[g] or model.geom_conaffinity[g])]
    out = {}
    for name, site in points.items():
        p = data.site_xpos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)]
        out[name] = tuple(model.geom(g).name for g in robot_geoms
                          if model.geom(g).name and _inside(model, data, g, p))
    return out


def _inside(model: mujoco.MjModel, data: mujoco.MjData, geom: int, point: np.ndarray, tol: float = 1e-6) -> bool:
    """Whether `point` (world) lies in the geom's volume (primitive shapes; others: their bounding sphere)."""
    g = mujoco.mjtGeom
    p = data.geom_xmat[geom].reshape(3, 3).T @ (point - data.geom_xpos[geom])  # geom frame
    size, kind = model.geom_size[geom], model.geom_type[geom]
    if kind == g.mjGEOM_SPHERE:
        return bool(np.linalg.norm(p) <= size[0] + tol)
    if kind == g.mjGEOM_CAPSULE:
        axis = np.array([0.0, 0.0, np.clip(p[2], -size[1], size[1])])
        return bool(np.linalg.norm(p - axis) <= size[0] + tol)
    if kind == g.mjGEOM_CYLINDER:
        return bool(np.hypot(p[0], p[1]) <= size[0] + tol and abs(p[2]) <= size[1] + tol)
    if kind == g.mjGEOM_BOX:
        return bool(np.all(np.abs(p) <= size + tol))
    if kind == g.mjGEOM_ELLIPSOID:
        return bool(np.sum((p / size) ** 2) <= 1.0 + tol)
    return bool(np.linalg.norm(p) <= model.geom_rbound[geom] + tol)


def _check_joint_order(config: RobotConfig, model_joints: list[str], where: str) -> None:
    expected = config.joint_names
    if model_joints == expected:
        return
    missing = [j for j in expected if j not in model_joints]
    extra = [j for j in model_joints if j not in expected]
    if missing or extra:
        raise ModelError(
            f"{where}: joints of the model and of robot '{config.name}' differ; "
            f"in the config but not the model: {missing}; in the model but not the config: {extra}"
        )
    raise ModelError(
        f"{where}: joint order differs from robot '{config.name}' config; "
        f"model order: {model_joints}; config order: {expected}"
    )


def _check_names(spec: mujoco.MjSpec, config: RobotConfig) -> None:
    """Every site, body and keyframe the config names must exist in the MJCF."""
    where = str(config.mjcf_path)
    sites = {config.imu_site, *config.end_effectors.values()}
    for foot in config.feet:
        sites |= {foot.sole_site, *foot.corner_sites}
    missing = sorted(sites - {s.name for s in spec.sites})
    if missing:
        raise ModelError(f"{where}: robot '{config.name}' config names sites missing from the model: {missing}")
    bodies = {config.base_body, *(f.body for f in config.feet)}
    missing = sorted(bodies - {b.name for b in spec.bodies})
    if missing:
        raise ModelError(f"{where}: robot '{config.name}' config names bodies missing from the model: {missing}")
    if config.stand_keyframe not in {k.name for k in spec.keys}:
        raise ModelError(f"{where}: keyframe '{config.stand_keyframe}' not found in the model")


def stand_qpos(model: mujoco.MjModel, config: RobotConfig) -> np.ndarray:
    kid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, config.stand_keyframe)
    return model.key_qpos[kid].copy()


def sensor_slice(model: mujoco.MjModel, name: str) -> slice:
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)
    if sid < 0:
        raise KeyError(f"no sensor named '{name}'")
    adr = int(model.sensor_adr[sid])
    return slice(adr, adr + int(model.sensor_dim[sid]))


def _first_line(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return " ".join(text[:3]) if text else type(exc).__name__
