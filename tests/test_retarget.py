"""Human motion retargeting: the BVH and SMPL readers on constructed clips with known joint
positions, leg-ratio speed scaling, feet on (not in) the ground, filters, and bad files."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from human_clips import walking_joints
from opt2skill.data.reader import Dataset
from opt2skill.data.validate import validate
from opt2skill.errors import DataError
from opt2skill.model import load_robot
from opt2skill.retarget.bvh import read_bvh
from opt2skill.retarget.motion import HumanMotion
from opt2skill.retarget.pipeline import retarget
from opt2skill.retarget.smpl import JOINTS, OFFSETS, read_smpl

BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT LeftUpLeg
  {
    OFFSET 10 0 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT LeftLeg
    {
      OFFSET 0 -40 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 -40 0
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0333333
0 90 0 0 0 0 0 0 0 0 0 0
5 90 0 0 0 0 0 90 0 0 0 0
"""


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


def test_bvh_reader_gives_the_known_joint_positions(tmp_path):
    path = tmp_path / "clip.bvh"
    path.write_text(BVH)
    m = read_bvh(path)  # centimetres (skeleton 80 units tall), y up -> metres, z up: (x, y, z) -> (z, x, y)
    assert m.joints == ("Hips", "LeftUpLeg", "LeftLeg", "LeftLeg_end") and m.fps == pytest.approx(30.0, rel=1e-4)
    p = m.positions
    assert np.allclose(p[0], [[0, 0, 0.9], [0, 0.1, 0.9], [0, 0.1, 0.5], [0, 0.1, 0.1]])
    # frame 2: root moved 5 cm along x; the hip turned 90 deg about x swings the leg to -z (file axes)
    assert np.allclose(p[1], [[0, 0.05, 0.9], [0, 0.15, 0.9], [-0.4, 0.15, 0.9], [-0.8, 0.15, 0.9]])


def test_smpl_reader_gives_the_known_joint_positions(tmp_path):
    poses = np.zeros((2, 156))  # SMPL-H layout: 52 joints
    poses[1, 3:6] = [np.pi / 2, 0, 0]  # left hip (joint 1) 90 deg about x
    trans = np.array([[1.0, 2.0, 0.9], [1.0, 2.0, 0.9]])
    path = tmp_path / "clip.npz"
    np.savez(path, poses=poses, trans=trans, mocap_framerate=120.0, betas=np.zeros(16))
    m = read_smpl(path, up="z")
    j = {name: i for i, name in enumerate(JOINTS)}
    assert m.fps == 120.0 and m.positions.shape == (2, 22, 3)
    assert np.allclose(m.positions[:, j["pelvis"]], trans)
    hip = trans[0] + OFFSETS[j["left_hip"]]
    assert np.allclose(m.positions[0, j["left_knee"]], hip + OFFSETS[j["left_knee"]])
    thigh = -OFFSETS[j["left_knee"]][1]
    assert np.allclose(m.positions[1, j["left_knee"]], hip + [0, 0, -thigh])  # y -> z under Rx(90)
    # a file with joint positions is read as is
    joints = np.random.default_rng(0).normal(size=(3, 24, 3))
    np.savez(tmp_path / "joints.npz", joints=joints, mocap_framerate=30)
    assert np.allclose(read_smpl(tmp_path / "joints.npz").positions, joints[:, :22])


def test_retargeted_torso_speed_is_scaled_by_the_leg_ratio_and_feet_stay_on_the_ground(robot):
    pos, fps = walking_joints(speed=0.8, clearance=0.12, hip_height=0.8)
    traj, errors = retarget(robot, HumanMotion(JOINTS, pos, fps, "constructed"))
    calib = traj.solver["calibration"]
    assert calib["human_leg"] == pytest.approx(0.8, abs=1e-6)
    ratio = calib["leg_ratio"]
    assert ratio == pytest.approx(calib["robot_leg"] / 0.8) and abs(ratio - 1) > 0.1
    speed = (traj.qpos[-1, 0] - traj.qpos[0, 0]) / traj.duration
    assert speed == pytest.approx(0.8 * ratio, rel=0.03)
    assert traj.params["speed"] == pytest.approx(0.8 * ratio, rel=0.03)
    assert traj.params["clearance"] == pytest.approx(0.12 * ratio, rel=0.1)
    feet = [list(traj.ee_names).index(f) for f in ("left_foot", "right_foot")]
    assert traj.ee_pos[:, feet, 2].min() > -1e-3  # sole centres never below the floor
    v = validate(robot, traj, task_errors=errors)
    assert v["figures"]["foot_penetration"] < 1.0 and v["figures"]["foot_slip"] < 1.0  # mm
    assert v["figures"]["task.ik_foot_error"] < 0.005
    assert (traj.source, traj.has_dynamics) == ("human", False)


def test_clips_outside_the_filters_are_rejected_with_their_reason(robot):
    pos, fps = walking_joints(speed=0.8, clearance=0.3, hip_height=0.9, duration=2.5)
    traj, errors = retarget(robot, HumanMotion(JOINTS, pos, fps, "high steps"))
    v = validate(robot, traj, task_errors=errors)
    assert not v["accepted"] and "task.clearance_out_of_range" in v["reasons"]
    assert "task.speed_out_of_range" not in v["reasons"]


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "opt2skill", "retarget", *args], capture_output=True, text=True,
                          timeout=120)


def test_cli_retargets_a_clip_and_refuses_a_bad_file_with_one_line(tmp_path):
    pos, fps = walking_joints(speed=1.0, clearance=0.13, hip_height=0.9, duration=3.0)
    clip = tmp_path / "walk.npz"
    np.savez(clip, joints=pos, mocap_framerate=fps)
    bad = tmp_path / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 zero\n")
    with pytest.raises(DataError, match="should be a number"):
        read_bvh(bad)
    r = _cli(str(bad), str(clip), "--out", str(tmp_path / "d"), "--quiet")
    assert r.returncode == 2 and "bad.bvh" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "d").exists() or not any((tmp_path / "d").iterdir())
    r = _cli(str(clip), "--out", str(tmp_path / "d"), "--quiet")
    assert r.returncode == 0, r.stderr
    assert "walk.npz:" in r.stdout
    ds = Dataset.open(tmp_path / "d", "accepted") if "1 accepted" in r.stdout else Dataset.open(tmp_path / "d", "rejected")
    meta = ds.meta(0)
    assert (meta.task, meta.source, meta.has_dynamics) == ("walk_human", "human", False)
    assert Path(meta.provenance["source_file"]).name == "walk.npz"


def test_a_longer_list_of_clips_extends_the_dataset_and_another_is_refused(tmp_path):
    """The clips already retargeted keep their indices and are not redone; a list that does not
    start with the dataset's files is one line, exit 2, and changes nothing."""
    first, second = tmp_path / "walk.npz", tmp_path / "walk2.npz"  # sorted in this order
    for clip, speed in ((first, 1.0), (second, 0.8)):
        pos, fps = walking_joints(speed=speed, clearance=0.13, hip_height=0.9, duration=2.5)
        np.savez(clip, joints=pos, mocap_framerate=fps)
    out = tmp_path / "d"
    assert _cli(str(first), "--out", str(out), "--quiet").returncode == 0
    r = _cli(str(second), str(first), "--out", str(out), "--quiet")
    assert r.returncode == 0, r.stderr
    assert "walk2.npz:" in r.stdout and "walk.npz:" not in r.stdout  # only the new clip was retargeted
    header = json.loads((out / "dataset.json").read_text())
    assert header["identity"]["files"] == ["walk.npz", "walk2.npz"]
    r = _cli(str(second), "--out", str(out), "--quiet")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "holds a different dataset" in r.stderr
    assert json.loads((out / "dataset.json").read_text())["identity"]["files"] == ["walk.npz", "walk2.npz"]
