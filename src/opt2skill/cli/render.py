"""`opt2skill render`: an MP4 of a motion, rendered offscreen."""

from __future__ import annotations

from pathlib import Path

import typer

from opt2skill.cli.console import console
from opt2skill.errors import ConfigError

app = typer.Typer()


@app.command()
def render(
    source: Path = typer.Argument(..., help="A dataset directory (its trajectory is replayed kinematically)."),
    index: int = typer.Option(None, help="Trajectory index (as generated); default: the first stored."),
    out: Path = typer.Option(None, help="MP4 file (default: SOURCE/render_INDEX.mp4)."),
    fps: int = typer.Option(30, min=1, max=240, help="Frames per second of the video."),
    robot: str = typer.Option(None, help="Robot name or robot.yaml (default: the one the data names)."),
) -> None:
    """Render a reference trajectory to MP4 without a display (EGL)."""
    from opt2skill.data.reader import Dataset
    from opt2skill.eval.render import render_video
    from opt2skill.model import load_robot

    if not (source / "dataset.json").is_file():
        raise ConfigError(f"{source} is not a dataset directory (no dataset.json)")
    ds = Dataset.open(source)
    if not len(ds):
        raise ConfigError(f"{source} has no accepted trajectories to render")
    position = 0 if index is None else ds.position(index)
    traj = ds[position]
    path = out or source / f"render_{int(ds.indices[position]):06d}.mp4"
    render_video(load_robot(robot or traj.robot), traj.qpos, path, fps=fps)
    console.print(f"wrote {path} ({traj.duration:.1f} s of motion)")
