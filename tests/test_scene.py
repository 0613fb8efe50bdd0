"""Scenes: JSON both ways, clear errors, and MuJoCo models that are the scene they describe."""

import json

import mujoco
import numpy as np
import pytest

from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.scene import Box, Desk, Flat, RoughGround, Scene, Shelf, Slope, Stairs, build_model, prop_qpos
from opt2skill.scene.build import add_prop


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


def settle(model, robot, seconds, robot_x=-3.0):
    """Step the scene with the robot standing out of the way; returns the final MjData."""
    d = mujoco.MjData(model)
    d.qpos[: robot.nq] = robot.stand_qpos
    d.qpos[0] = robot_x
    for _ in range(int(seconds / model.opt.timestep)):
        mujoco.mj_step(model, d)
    return d


def ray_heights(model, xy):
    """What a ray straight down from 5 m hits first, the robot standing out of the way."""
    d = mujoco.MjData(model)
    d.qpos[0] = 30.0
    mujoco.mj_kinematics(model, d)
    hit = np.zeros(1, np.int32)
    return np.array([5.0 - mujoco.mj_ray(model, d, np.array([x, y, 5.0]), np.array([0.0, 0.0, -1.0]), None, 1, -1, hit)
                     for x, y in xy])


def test_a_scene_round_trips_through_json():
    scene = Scene(Stairs(0.12, step_length=0.35, start=1.5, n_steps=4, down=True),
                  (Box((0.3, 0.25, 0.2), mass=4.9, pos=(0.6, 0.1, 0.9), yaw=0.3, friction=0.8),
                   Shelf(pos=(0.6, 0.0), boards=(0.4, 0.8), name="shelf_from"),
                   Shelf(pos=(-0.2, 1.0), yaw=1.57, boards=(1.2,), name="shelf_to"), Desk(height=0.92)))
    raw = json.loads(json.dumps(scene.to_dict()))
    assert raw["terrain"]["kind"] == "stairs" and [p["kind"] for p in raw["props"]] == ["box", "shelf", "shelf", "desk"]
    assert Scene.from_dict(raw) == scene
    rough = Scene(RoughGround(amplitude=0.04, seed=7))
    back = Scene.from_dict(json.loads(json.dumps(rough.to_dict())))
    assert back == rough and np.array_equal(back.ground.heights, rough.ground.heights)
    assert Scene.from_dict({}) == Scene() and Scene().terrain == Flat()
    # Fields left out take their defaults.
    assert Scene.from_dict({"terrain": {"kind": "slope", "angle_deg": 10}}) == Scene(Slope(10.0))


@pytest.mark.parametrize("raw, message", [
    ({"props": [{"kind": "ball"}]}, "unknown prop kind 'ball'; kinds: box, shelf, desk"),
    ({"terrain": {"kind": "lava"}}, "unknown terrain kind 'lava'; kinds: flat, rough, stairs, slope"),
    ({"terrain": {"kind": "stairs"}}, r"scene terrain 'stairs' needs the fields \['step_height'\]"),
    ({"terrain": {"kind": "stairs", "step_height": 0.5}}, r"stair step height must be in \[0, 0.3\] m, got 0.5"),
    ({"terrain": {"kind": "stairs", "step_height": 0.1, "risers": 3}}, r"unknown fields \['risers'\]"),
    ({"terrain": {"kind": "stairs", "step_height": "high"}}, "field 'step_height' must be a number"),
    ({"terrain": {"kind": "stairs", "step_height": 0.1, "down": 1}}, "field 'down' must be true or false"),
    ({"terrain": {"kind": "rough", "amplitude": 0.5}}, r"rough terrain amplitude must be in \[0, 0.2\] m"),
    ({"props": [{"kind": "box", "mass": 80}]}, r"box 'box': mass must be in \[0.01, 50\] kg, got 80.0"),
    ({"props": [{"kind": "box", "pos": [0.5, 0.0]}]}, "box 'box': pos must be 3 numbers"),
    ({"props": [{"kind": "box", "pos": [0.5, 0.0, 0.05]}]}, "its bottom is below z = 0"),
    ({"props": [{"kind": "shelf", "boards": [0.8, 0.4]}]}, "board heights must increase"),
    ({"props": [{"kind": "desk", "name": "my desk"}]}, "a prop name must be letters, digits or '_'"),
    ({"props": [{"kind": "box"}, {"kind": "box", "pos": [1.0, 0.0, 0.5]}]}, "two props are named 'box'"),
    ({"props": {"kind": "box"}}, "scene props must be a list"),
    ({"wall": []}, r"unknown scene keys \['wall'\]"),
])
def test_bad_scenes_get_one_clear_error(raw, message):
    with pytest.raises(ConfigError, match=message):
        Scene.from_dict(raw)


def test_an_unknown_prop_object_is_refused():
    with pytest.raises(ConfigError, match="unknown prop 'door'; props: box, shelf, desk"):
        Scene(props=("door",))


def test_a_prop_can_be_moved_to_test_a_motion_in_another_scene():
    scene = Scene(props=(Desk(height=0.95), Box(name="box")))
    moved = scene.with_prop("desk", height=0.9)
    assert moved.prop("desk").height == 0.9 and moved.prop("desk").boards == (0.9,)
    assert moved.prop("box") is scene.prop("box") and scene.prop("desk").height == 0.95
    assert [s.centre[2] for s in moved.surfaces() if s.prop == "desk"] == pytest.approx([0.9])
    with pytest.raises(ConfigError, match=r"prop 'desk' \(desk\) has no fields \['hieght'\]; fields: depth, "):
        scene.with_prop("desk", hieght=0.9)
    with pytest.raises(ConfigError, match="the scene has no prop 'table'"):
        scene.with_prop("table", height=0.9)
    with pytest.raises(ConfigError, match="height"):
        scene.with_prop("desk", height=0.01)


@pytest.mark.parametrize("down", [False, True])
def test_stairs_geoms_sit_at_the_heights_the_scene_reports(robot, down):
    stairs = Stairs(0.13, step_length=0.3, start=1.0, n_steps=4, landing=1.0, down=down)
    scene = Scene(stairs)
    model = build_model(robot, scene)
    # The middle of every tread, both sides of every nosing, and the floor beyond.
    x = np.concatenate([stairs.start + stairs.step_length * (np.arange(-2, 6) + 0.5),
                        (stairs.start + stairs.step_length * np.arange(4)[:, None] + [-0.01, 0.01]).ravel()])
    xy = np.stack([x, np.full_like(x, 0.2)], -1)
    heights = scene.ground_height(xy)
    assert np.abs(ray_heights(model, xy) - heights).max() < 1e-9
    # Treads are multiples of the step height, from the floor to the top.
    assert set(np.round(heights / 0.13, 9)) == {0.0, 1.0, 2.0, 3.0, 4.0}
    top_side = x < stairs.start if down else (x > stairs.start + 3 * stairs.step_length) & (x < stairs.end)
    assert np.allclose(heights[top_side], 4 * 0.13)


def test_a_box_is_a_free_body_with_its_mass_held_only_by_contact(robot):
    box = Box((0.3, 0.25, 0.2), mass=4.9, pos=(0.6, 0.0, 0.9), yaw=0.4)
    shelf = Shelf(pos=(0.6, 0.0), boards=(0.4, 0.8))
    model = build_model(robot, Scene(props=(box, shelf)))
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "box")
    assert model.body_mass[body] == pytest.approx(4.9)
    assert model.body_inertia[body] == pytest.approx(4.9 / 12 * np.array([0.25**2 + 0.2**2, 0.3**2 + 0.2**2,
                                                                           0.3**2 + 0.25**2]))
    joint = model.body_jntadr[body]
    assert model.body_jntnum[body] == 1 and model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_FREE
    assert model.neq == 0  # nothing welds it
    # The robot's state leads; the box's follows.
    assert model.nq == robot.nq + 7 and prop_qpos(model, "box") == slice(robot.nq, robot.nq + 7)
    # The box's bottom face lies on the top board, and the board holds it still.
    bottom = next(s for s in box.surfaces() if s.name == "bottom")
    board = next(s for s in shelf.surfaces() if s.name == "board_1")
    assert board.contains(bottom.centre) and np.allclose(bottom.normal, -board.normal)
    d = settle(model, robot, 1.0)
    pose = d.qpos[prop_qpos(model, "box")]
    assert np.abs(pose[:3] - box.pos).max() < 1e-3
    # Without the shelf it falls to the floor.
    d = settle(build_model(robot, Scene(props=(box,))), robot, 1.0)
    assert d.qpos[robot.nq + 2] == pytest.approx(0.1, abs=2e-3)


def test_shelves_and_desks_are_fixed_and_collide_where_their_surfaces_say(robot):
    shelf = Shelf(pos=(0.8, -0.5), yaw=0.5, boards=(0.35, 0.9))
    desk = Desk(pos=(2.0, 1.0), height=0.88)
    model = build_model(robot, Scene(props=(shelf, desk)))
    assert model.nq == robot.nq and model.nbody == robot.mj_model.nbody
    for surface in shelf.surfaces()[-1:] + desk.surfaces():  # the top board hides the one below
        inside = surface.centre + 0.8 * surface.half_size @ surface.axes * [[1], [-1]]  # two points near corners
        assert np.allclose(ray_heights(model, inside[:, :2]), surface.centre[2], atol=1e-9), surface.name
    assert shelf.surfaces()[0].contains(shelf.surfaces()[0].centre + [0, 0, 1e-7])
    assert not shelf.surfaces()[0].contains(shelf.surfaces()[0].centre + [0, 0, 0.01])


def test_flat_scene_is_the_robots_own_model(robot):
    model = build_model(robot, Scene())
    assert (model.nq, model.nv, model.nu, model.ngeom, model.nsensordata) == (
        robot.nq, robot.nv, robot.nu, robot.mj_model.ngeom, robot.mj_model.nsensordata)
    assert np.allclose(model.geom_size, robot.mj_model.geom_size)


@pytest.mark.parametrize("torsion", [0.0, 0.02])
def test_a_box_squeezed_between_two_points_turns_about_them_only_without_torsion(torsion):
    """Two fixed spheres press on the box's side faces (the hands' grasp); a spin about the line
    between them keeps going with point contacts, and stops with the box's torsional friction."""
    spec = mujoco.MjSpec()
    spec.option.gravity = [0.0, 0.0, 0.0]
    add_prop(spec, Box((0.16, 0.3, 0.2), mass=1.0, pos=(0.0, 0.0, 1.0), torsion=torsion))
    for side in (1, -1):  # each sphere 2 mm into its face: a squeeze of tens of newtons
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.03, 0, 0], pos=[0.0, side * 0.178, 1.0],
                                friction=[1.0, 0.0, 0.0])
    model = spec.compile()
    d = mujoco.MjData(model)
    d.qvel[4] = 2.0  # rad/s about y, the line between the spheres
    for _ in range(500):
        mujoco.mj_step(model, d)
    spin = abs(d.qvel[4])
    assert (spin > 1.0) if torsion == 0.0 else (spin < 0.05)
