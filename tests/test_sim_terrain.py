"""Terrains are what they claim in MuJoCo, per world, and the robot starts on them and stands."""

import mujoco
import numpy as np
import pytest

from opt2skill.errors import ConfigError
from opt2skill.geometry import tilt_angle
from opt2skill.model import load_robot
from opt2skill.model.standing import feedforward_ctrl
from opt2skill.model.statics import gravity_compensation
from opt2skill.sim import Flat, MujocoBatchedSim, SimConfig, Slope, Stairs, TerrainGrid, rough

GRID = TerrainGrid(x_range=(-2.0, 4.0), y_range=(-2.0, 2.0))


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


def sim_with(robot, terrains, qpos):
    """One world per terrain, robots at `qpos` (n, nq)."""
    n = len(terrains)
    sim = MujocoBatchedSim(robot, n, SimConfig(nthread=1), terrains=terrains)
    p = sim.params
    p.terrain = np.arange(n)
    out = sim.reset(np.arange(n), qpos, np.zeros((n, robot.nv)), params=p)
    return sim, out


def ray_heights(model, qpos, xy):
    d = mujoco.MjData(model)
    d.qpos[:] = qpos
    mujoco.mj_forward(model, d)
    hit = np.zeros(1, np.int32)
    return np.array([5.0 - mujoco.mj_ray(model, d, np.array([x, y, 5.0]), np.array([0.0, 0.0, -1.0]), None, 1, -1, hit)
                     for x, y in xy])


def test_every_world_collides_with_the_surface_its_terrain_describes(robot):
    """Rays cast down in each world's model hit its own terrain at the height the terrain reports."""
    terrains = [Flat(), rough(GRID, 0.03, seed=1), rough(GRID, 0.03, seed=2), Stairs(0.12, n_steps=5),
                Slope(15.0, length=2.0)]
    qpos = np.tile(robot.stand_qpos, (len(terrains), 1))
    qpos[:, 0] = 30.0  # the robots stand out of the rays' way
    sim, _ = sim_with(robot, terrains, qpos)
    xy = np.random.default_rng(0).uniform([-1.9, -1.9], [3.9, 1.9], size=(200, 2))
    reported = sim.terrain_height(np.broadcast_to(xy, (len(terrains), 200, 2)))
    for w, terrain in enumerate(terrains):
        tol = 1e-7 if w in (1, 2) else 1e-12  # heightfield data is float32
        assert np.abs(ray_heights(sim.models[w], qpos[w], xy) - reported[w]).max() < tol, terrain.name
    assert np.abs(reported[1] - reported[2]).max() > 0.01  # two rough worlds, two different surfaces
    # Switching a world to another terrain replaces its ground entirely.
    p = sim.params
    p.terrain[1] = 0
    sim.set_params(np.arange(len(terrains)), p)
    assert np.allclose(ray_heights(sim.models[1], qpos[1], xy), 0.0)


def test_stairs_and_slope_have_the_requested_geometry():
    stairs = Stairs(0.15, step_length=0.3, start=1.0, n_steps=4, landing=2.0)
    treads = 1.0 + 0.3 * np.arange(4) + 0.15
    assert np.allclose(stairs.height(np.c_[treads, np.zeros(4)]), [0.15, 0.30, 0.45, 0.60])
    around = np.array([[0.99, 0.0], [1.01, 0.0], [3.0, 0.0], [4.0, 0.0]])  # before, first step, landing, after
    assert np.allclose(stairs.height(around), [0, 0.15, 0.6, 0])
    slope = Slope(20.0, start=1.0, length=3.0)
    x = np.array([0.5, 1.0, 2.0, 4.0, 5.0])
    assert np.allclose(slope.height(np.c_[x, np.zeros(5)]), np.tan(np.radians(20)) * np.clip(x - 1.0, 0, 3.0))


def test_rough_terrain_is_seeded_and_bounded():
    a, b, c = rough(GRID, 0.02, seed=4), rough(GRID, 0.02, seed=4), rough(GRID, 0.02, seed=5)
    assert np.array_equal(a.heights, b.heights) and not np.array_equal(a.heights, c.heights)
    assert a.heights.shape == (GRID.nrow, GRID.ncol)
    assert np.abs(a.heights).max() <= 0.02 and a.heights.std() > 0.005
    with pytest.raises(ConfigError, match="z range"):
        rough(TerrainGrid(z_range=(-0.01, 0.01)), 0.05)


@pytest.mark.parametrize(
    "make, x",
    [(lambda: Flat(), 0.0), (lambda: rough(GRID, 0.01, seed=0), 0.0),
     (lambda: Stairs(0.12, step_length=0.35, start=1.0), 1.0 + 0.35 * 1.5 + 0.04),  # feet on the 2nd tread
     (lambda: Slope(5.0, start=0.5), 2.0)],
    ids=["flat", "rough", "stairs", "slope"],
)
def test_robot_starts_on_the_terrain_and_stands(robot, make, x):
    terrain = make()
    qpos = robot.stand_qpos[None].copy()
    qpos[0, 0] = x
    if isinstance(terrain, Slope):  # feet parallel to the incline
        for joint in ("left_ankle_pitch", "right_ankle_pitch"):
            qpos[0, 7 + robot.config.joint_names.index(joint)] = -np.radians(terrain.angle_deg)
    sim, out = sim_with(robot, [terrain], qpos)
    corners = [[robot.site_id(s) for s in f.corner_sites] for f in robot.config.feet]
    d = mujoco.MjData(sim.models[0])
    d.qpos[:] = out.qpos[0]
    mujoco.mj_kinematics(sim.models[0], d)
    soles = d.site_xpos[np.ravel(corners)]
    clearance = soles[:, 2] - terrain.height(soles[:, :2])
    assert clearance.min() > -1e-9 and clearance.min() < 0.05  # on it, not inside it nor far above
    targets = feedforward_ctrl(robot, qpos[0], gravity_compensation(robot, qpos[0]).torque)[None]
    for _ in range(100):
        out = sim.step(targets)
    weight = out.contact_wrench_mean[0, :, 2].sum() / 9.81
    height = out.qpos[0, 2] - terrain.height(out.qpos[0, :2])
    assert not out.unstable[0]
    assert abs(weight / robot.mj_model.body_mass.sum() - 1.0) < 0.2
    assert 0.9 < height < 1.1 and np.degrees(tilt_angle(out.qpos[0, 3:7])) < 10.0


def test_bad_terrains_are_clear_errors(robot):
    with pytest.raises(ConfigError, match="step height"):
        Stairs(0.5)
    with pytest.raises(ConfigError, match="slope angle"):
        Slope(-5.0)
    with pytest.raises(ConfigError, match="share one TerrainGrid"):
        MujocoBatchedSim(robot, 1, SimConfig(nthread=1), terrains=[rough(GRID, 0.01), rough(TerrainGrid(), 0.01)])
    with pytest.raises(ConfigError, match="resolution"):
        TerrainGrid(resolution=0.0)


def test_world_bounding_tree_encloses_the_moved_boxes(robot):
    """MuJoCo's midphase culls with the world body's bounding-volume tree, built when the boxes sat
    at the origin: after placing them, every node must enclose its geom's box or its children."""
    sim, _ = sim_with(robot, [Stairs(0.15, n_steps=4), Slope(12.0)], np.tile(robot.stand_qpos, (2, 1)))
    for m in sim.models:
        adr, num = m.body_bvhadr[0], m.body_bvhnum[0]
        box = m.bvh_aabb[adr:adr + num]
        lo, hi = box[:, :3] - box[:, 3:], box[:, :3] + box[:, 3:]
        for node in range(num):
            geom = m.bvh_nodeid[adr + node]
            if geom >= 0 and m.geom_type[geom] == mujoco.mjtGeom.mjGEOM_BOX:
                rot = np.zeros(9)
                mujoco.mju_quat2Mat(rot, m.geom_quat[geom])
                signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
                corners = m.geom_pos[geom] + (signs * m.geom_size[geom]) @ rot.reshape(3, 3).T
                assert np.all(corners >= lo[node] - 1e-9) and np.all(corners <= hi[node] + 1e-9)
            elif geom < 0:
                for child in m.bvh_child[adr + node]:
                    assert np.all(lo[child] >= lo[node] - 1e-9) and np.all(hi[child] <= hi[node] + 1e-9)
