"""Offscreen video of a real trajectory, with and without the reference ghost."""

import subprocess
import sys

import imageio
import numpy as np
import pytest

from opt2skill.eval.render import render_video, scene_model
from opt2skill.model import load_robot
from opt2skill.tasks import get_task


@pytest.fixture(scope="module")
def squat():
    robot = load_robot("digit")
    return robot, get_task("squat", robot).solve({"depth": 0.12}, seed=0)


def test_video_shows_the_motion(squat, tmp_path):
    robot, traj = squat
    path = render_video(robot, traj.qpos, tmp_path / "squat.mp4", fps=20, size=(120, 160))
    reader = imageio.get_reader(path)
    frames = [np.asarray(f, dtype=float) for f in reader]
    assert len(frames) == int(traj.duration * 20) + 1
    assert all(f.shape == (120, 160, 3) and f.std() > 5 for f in frames)  # not blank
    # The squat moves the robot: the middle frame (lowest) differs from the first (standing).
    assert np.abs(frames[len(frames) // 2] - frames[0]).mean() > 1.0
    assert not list(tmp_path.glob("*.tmp*"))


def test_ghost_is_a_second_non_colliding_robot(squat, tmp_path):
    robot, traj = squat
    model = scene_model(robot, ghost=True)
    assert model.nq == 2 * robot.nq and model.nu == robot.nu
    ghost = [i for i in range(model.ngeom) if model.geom(i).name.startswith("ghost/")]
    assert ghost and not model.geom_contype[ghost].any() and not model.geom_conaffinity[ghost].any()
    shifted = traj.qpos.copy()
    shifted[:, 1] += 0.6
    with_ghost = render_video(robot, traj.qpos, tmp_path / "g.mp4", ghost_qpos=shifted, fps=10, size=(120, 160))
    alone = render_video(robot, traj.qpos, tmp_path / "a.mp4", fps=10, size=(120, 160))
    first = [np.asarray(imageio.get_reader(p).get_data(0), dtype=float) for p in (with_ghost, alone)]
    assert np.abs(first[0] - first[1]).mean() > 1.0


def test_render_command_on_a_dataset(tmp_path):
    data = tmp_path / "squat"
    run = [sys.executable, "-m", "opt2skill"]
    subprocess.run([*run, "generate", "squat", "--n", "1", "--workers", "1", "--out", str(data), "--quiet"],
                   check=True, capture_output=True, timeout=300)
    result = subprocess.run([*run, "render", str(data), "--fps", "10", "--out", str(tmp_path / "v.mp4")],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "v.mp4").stat().st_size > 1000
    bad = subprocess.run([*run, "render", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "not a dataset directory" in bad.stderr
