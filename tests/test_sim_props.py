"""Props in the batched simulator: per-world slots that show each world's scene as `build_model` builds
it, free boxes that fall and rest under real physics, parked slots that stay put, and the robot's
outputs unchanged by slots it does not use."""

import mujoco
import numpy as np
import pytest

from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.scene import Box, Desk, Scene, Shelf, build_model
from opt2skill.sim import MujocoBatchedSim, SimConfig, WorldParams
from opt2skill.sim.devices import make_sim

SHELF_AND_BOX = (Shelf(pos=(1.2, 0.5), boards=(0.5, 0.9)), Box(mass=2.0, size=(0.2, 0.3, 0.2), pos=(1.2, 0.5, 0.65)))
DESK_AND_TWO_BOXES = (Desk(pos=(-1.0, 0.8), yaw=0.4), Box(pos=(-1.0, 0.8, 1.2), name="a"),
                      Box(mass=0.5, size=(0.1, 0.1, 0.1), pos=(-1.0, 0.8, 1.6), name="b"))


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


@pytest.fixture(scope="module")
def sim(robot):
    """Three worlds: no props, the shelf and box, the desk and two boxes."""
    s = MujocoBatchedSim(robot, 3, SimConfig(nthread=1), prop_sets=[(), SHELF_AND_BOX, DESK_AND_TWO_BOXES])
    params = WorldParams.nominal(3, s.nbody, s.nu)
    params.props = np.array([0, 1, 2])
    stand = np.tile(robot.stand_qpos, (3, 1))
    s.reset(np.arange(3), stand, np.zeros((3, robot.nv)), params=params)
    yield s
    s.close()


def shown_boxes(model):
    """(centre, half size, quaternion) of every collidable box geom, sorted by centre."""
    out = []
    for g in range(model.ngeom):
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX and model.geom_contype[g] and model.geom_bodyid[g] == 0:
            out.append(np.r_[model.geom_pos[g], np.abs(model.geom_size[g]), model.geom_quat[g] * np.sign(model.geom_quat[g, 0])])
    return np.array(sorted(out, key=lambda r: tuple(np.round(r[:3], 6))))


def test_each_world_shows_its_own_props_as_the_scene_builds_them(robot, sim):
    assert sim.props.nfree == 2 and sim.props.nfixed == max(len(p.geoms()) for p in (SHELF_AND_BOX[0], DESK_AND_TWO_BOXES[0]))
    assert len(shown_boxes(sim.models[0])) == 0
    for world, props in ((1, SHELF_AND_BOX), (2, DESK_AND_TWO_BOXES)):
        reference = build_model(robot, Scene(props=props))
        np.testing.assert_allclose(shown_boxes(sim.models[world]), shown_boxes(reference), atol=1e-12)
        boxes = [p for p in props if not p.fixed]
        state = sim.reset([world], robot.stand_qpos[None], np.zeros((1, robot.nv)))
        for k, box in enumerate(boxes):
            body = mujoco.mj_name2id(reference, mujoco.mjtObj.mjOBJ_BODY, box.name)
            slot = mujoco.mj_name2id(sim.models[world], mujoco.mjtObj.mjOBJ_BODY, f"props_free_{k}")
            assert sim.models[world].body_mass[slot] == pytest.approx(reference.body_mass[body])
            np.testing.assert_allclose(sim.models[world].body_inertia[slot], reference.body_inertia[body])
            np.testing.assert_allclose(state.prop_pose[0, k], np.r_[box.geoms()[0].centre, box.geoms()[0].quat])
        np.testing.assert_array_equal(sim.props.used(world), np.arange(2) < len(boxes))
    assert state.qpos.shape == (1, robot.nq) and state.qvel.shape == (1, robot.nv)


def test_boxes_rest_on_their_boards_and_unused_slots_stay_put(robot, sim):
    stand = np.tile(robot.stand_qpos, (3, 1))
    start = sim.reset(np.arange(3), stand, np.zeros((3, robot.nv)))
    for _ in range(400):  # 2 s
        out = sim.step(stand[:, 7:])
    assert not out.unstable.any()
    # The parked slots (both in world 0, the second in world 1) never move at all.
    np.testing.assert_array_equal(out.prop_pose[0], start.prop_pose[0])
    np.testing.assert_array_equal(out.prop_pose[1, 1], start.prop_pose[1, 1])
    assert np.abs(out.prop_vel[0]).max() == 0.0
    # The box on the shelf's lower board stays on it (sinking into it by less than a millimetre) ...
    assert out.prop_pose[1, 0, 2] == pytest.approx(0.5 + 0.1, abs=1e-3)
    # ... and box a, dropped from 1.2 m, has fallen onto the desk (top 0.9 m), with b on top of it.
    assert out.prop_pose[2, 0, 2] == pytest.approx(0.9 + 0.15, abs=5e-3)
    assert out.prop_pose[2, 1, 2] == pytest.approx(0.9 + 0.3 + 0.05, abs=1e-2)


def test_a_world_without_props_steps_exactly_as_a_simulator_without_slots(robot, sim):
    plain = MujocoBatchedSim(robot, 1, SimConfig(nthread=1))
    stand = robot.stand_qpos[None]
    targets = np.tile(robot.stand_qpos[7:], (3, 1)) + 0.05 * np.sin(np.arange(robot.nu))
    sim.reset(np.arange(3), np.tile(stand, (3, 1)), np.zeros((3, robot.nv)))
    plain.reset([0], stand, np.zeros((1, robot.nv)))
    for _ in range(50):
        a, b = sim.step(targets), plain.step(targets[:1])
    np.testing.assert_array_equal(a.qpos[0], b.qpos[0])
    np.testing.assert_array_equal(a.contact_wrench[0], b.contact_wrench[0])
    assert b.prop_pose.shape == (1, 0, 7)
    plain.close()


def test_a_reset_places_the_boxes_it_is_given_and_keeps_unused_slots_parked(robot, sim):
    pose = np.array([[[0.4, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0], [5.0, 5.0, 5.0, 1.0, 0.0, 0.0, 0.0]]])
    out = sim.reset([1], robot.stand_qpos[None], np.zeros((1, robot.nv)), prop_pose=pose,
                    prop_vel=np.ones((1, 2, 6)))
    np.testing.assert_allclose(out.prop_pose[0, 0], pose[0, 0])
    np.testing.assert_allclose(out.prop_vel[0, 0], 1.0)
    # The set has one box: the second slot stays parked and still whatever was asked.
    np.testing.assert_array_equal(out.prop_vel[0, 1], 0.0)
    assert out.prop_pose[0, 1, 2] == -10.0
    with pytest.raises(ConfigError, match="prop_pose must have shape"):
        sim.reset([1], robot.stand_qpos[None], np.zeros((1, robot.nv)), prop_pose=pose[:, :1])
    with pytest.raises(ConfigError, match="props indices 0 to 2"):
        bad = WorldParams.nominal(1, sim.nbody, sim.nu)
        bad.props = np.array([3])
        sim.set_params([0], bad)


def test_the_warp_backend_refuses_props_with_one_clear_error(robot):
    with pytest.raises(ConfigError, match=r"Warp backend does not simulate props yet.*\['box', 'shelf'\].*--device cpu"):
        make_sim(robot, 2, SimConfig(), device="cuda", prop_sets=[(), SHELF_AND_BOX])
