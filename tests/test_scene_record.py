"""Every trajectory carries its scene: through the HDF5 file, and into the MuJoCo replay."""

import h5py
import mujoco
import numpy as np
import pytest

from opt2skill.data.record import build_trajectory
from opt2skill.data.replay import Replayer
from opt2skill.data.trajfile import read_meta, read_trajectory, write_trajectory
from opt2skill.errors import DataError
from opt2skill.model import load_robot
from opt2skill.model.statics import gravity_compensation
from opt2skill.scene import Box, Scene, Shelf, Stairs, prop_qpos

# The robot stands on the top landing of stairs going down (0.4 m up), a box on a shelf beside it.
LANDING = 4 * 0.1
SCENE = Scene(Stairs(0.1, start=1.0, n_steps=4, down=True),
              (Box(mass=2.0, pos=(0.3, 1.0, LANDING + 0.5 + 0.15)), Shelf(pos=(0.3, 1.0), boards=(LANDING + 0.5,))))


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


def standing(robot, scene, seconds=0.5, lift=0.0):
    """A reference of the robot standing still `lift` m up, gravity compensated."""
    n = int(seconds * 200) + 1
    qpos = np.tile(robot.stand_qpos, (n, 1))
    qpos[:, 2] += lift
    balance = gravity_compensation(robot, robot.stand_qpos)
    return build_trajectory(
        robot, qpos, np.zeros((n, robot.nv)), np.tile(balance.torque, (n, 1)), np.tile(balance.wrenches, (n, 1, 1)),
        np.ones((n, 2), bool), task="stand", contact_names=("left_foot", "right_foot"), params={}, seed=0,
        scene=scene,
    )


def test_a_scene_round_trips_through_the_record(robot, tmp_path):
    traj = standing(robot, SCENE, seconds=0.05, lift=LANDING)
    write_trajectory(tmp_path / "000000.h5", traj, 0)
    assert read_trajectory(tmp_path / "000000.h5").scene == SCENE
    assert read_meta(tmp_path / "000000.h5").scene == SCENE
    # A record made before scenes existed has no scene attribute: it was made on the flat floor.
    with h5py.File(tmp_path / "000000.h5", "r+") as f:
        del f["traj_000000"].attrs["scene"]
    assert read_trajectory(tmp_path / "000000.h5").scene == Scene()
    assert read_meta(tmp_path / "000000.h5").scene == Scene()
    assert standing(robot, None, seconds=0.05).scene == Scene()


def test_free_props_reference_poses_round_trip_and_old_files_have_none(robot, tmp_path):
    traj = standing(robot, SCENE, seconds=0.05, lift=LANDING)
    assert traj.prop_poses == {}
    pose = np.tile([0.3, 1.0, LANDING + 0.65, 1.0, 0.0, 0.0, 0.0], (traj.num_frames, 1))
    pose[:, 2] += np.linspace(0.0, 0.1, traj.num_frames)
    traj.prop_poses = {"box": pose}
    write_trajectory(tmp_path / "000000.h5", traj, 0)
    np.testing.assert_array_equal(read_trajectory(tmp_path / "000000.h5").prop_poses["box"], pose)
    with h5py.File(tmp_path / "000000.h5", "r+") as f:
        del f["traj_000000/prop_poses"]
    assert read_trajectory(tmp_path / "000000.h5").prop_poses == {}
    with pytest.raises(ValueError, match="not a moving prop of the scene"):  # the shelf is fixed
        build_trajectory(robot, traj.qpos, traj.qvel, traj.joint_torque, traj.contact_wrench, traj.contact_active,
                         task="stand", contact_names=traj.contact_names, params={}, seed=0, scene=SCENE,
                         prop_poses={"shelf": pose})


@pytest.mark.parametrize("stored, message", [
    ('{"terrain": {"kind": "lava"}}', "attribute 'scene' is not a valid scene: unknown terrain kind 'lava'"),
    ("{not json", "attribute 'scene' is not valid JSON"),
])
def test_a_malformed_scene_in_a_file_is_a_data_error(robot, tmp_path, stored, message):
    write_trajectory(tmp_path / "000000.h5", standing(robot, SCENE, seconds=0.05), 0)
    with h5py.File(tmp_path / "000000.h5", "r+") as f:
        f["traj_000000"].attrs["scene"] = stored
    for read in (read_trajectory, read_meta):
        with pytest.raises(DataError, match=message):
            read(tmp_path / "000000.h5")


def test_the_replay_runs_in_the_records_scene(robot):
    traj = standing(robot, SCENE, lift=LANDING)
    replayer = Replayer(robot, traj)
    assert replayer.model.nq == robot.nq + 7  # the box's free joint follows the robot
    nstep = int(0.5 / replayer.dt)
    (held,) = replayer.run([0], nstep)
    assert held.fall_time is None and held.base_error < 0.01 and held.foot_error < 0.01
    # The box stays on its shelf through a restart from a reference state.
    d = replayer.data
    replayer.initial_state(0)
    box = d.qpos[prop_qpos(replayer.model, "box")].copy()
    for ctrl in replayer.controls(0, nstep):  # the replay's own servo targets
        d.ctrl[:] = ctrl
        mujoco.mj_step(replayer.model, d)
    assert abs(d.qpos[2] - traj.qpos[0, 2]) < 0.01
    assert np.abs(d.qpos[prop_qpos(replayer.model, "box")][:3] - box[:3]).max() < 1e-3
    # The same motion replayed on the flat floor drops off the missing landing.
    traj.scene = Scene()
    (dropped,) = Replayer(robot, traj).run([0], nstep)
    assert dropped.fall_time is not None or dropped.base_error > 0.3
    # Feedback and whole-motion replays use the scene too.
    traj.scene = SCENE
    assert Replayer(robot, traj).full().fall_time is None


def test_render_draws_the_records_scene_and_ghost(robot, tmp_path):
    import imageio

    from opt2skill.eval.render import ghost_qpos_address, render_video, scene_model

    model = scene_model(robot, ghost=True, scene=SCENE)
    assert model.nq == 2 * robot.nq + 7 and ghost_qpos_address(model, robot) == robot.nq + 7
    traj = standing(robot, SCENE, seconds=0.1, lift=LANDING)
    shifted = traj.qpos.copy()
    shifted[:, 1] -= 0.8
    frames = {}
    for name, scene in (("scene", SCENE), ("flat", None)):
        path = render_video(robot, traj.qpos, tmp_path / f"{name}.mp4", ghost_qpos=shifted, fps=10, size=(120, 160),
                            scene=scene)
        frames[name] = np.asarray(imageio.get_reader(path).get_data(0), dtype=float)
    assert frames["scene"].std() > 5 and np.abs(frames["scene"] - frames["flat"]).mean() > 1.0
