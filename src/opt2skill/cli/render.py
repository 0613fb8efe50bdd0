"""`opt2skill render`: an MP4 of a motion, rendered offscreen: a dataset trajectory replayed
kinematically, or a run's policy tracking a reference with the reference as a translucent ghost."""

from __future__ import annotations

from pathlib import Path

import typer

from opt2skill.cli.console import console
from opt2skill.errors import ConfigError, DataError
from opt2skill.output_paths import check_output_file

app = typer.Typer()


@app.command()
def render(
    source: Path = typer.Argument(..., help="A dataset directory (replayed kinematically) or a run directory "
                                            "(its policy rolled out, the reference as a ghost)."),
    index: int = typer.Option(None, help="Trajectory index (as generated); default: the first stored (for a run: "
                                         "the first held-out reference)."),
    out: Path = typer.Option(None, help="MP4 file (default: SOURCE/render_INDEX.mp4)."),
    fps: int = typer.Option(30, min=1, max=240, help="Frames per second of the video."),
    robot: str = typer.Option(None, help="Robot name or robot.yaml (default: the one the data names)."),
    dataset: Path = typer.Option(None, "--dataset", help="For a run: where the reference comes from (default: the "
                                                         "run's training dataset)."),
    checkpoint: Path = typer.Option(None, help="For a run: a checkpoint file of it (default: the newest; "
                                               "RUN/distill/checkpoints/ holds the distilled actor)."),
) -> None:
    """Render a reference trajectory, or a policy's rollout beside its reference, to MP4 (EGL)."""
    from opt2skill.data.reader import Dataset
    from opt2skill.eval.render import render_video
    from opt2skill.model import load_robot

    if out is not None:
        check_output_file(out, suffix=".mp4")  # before the rollout and the rendering
    if (source / "run.json").is_file():
        _render_run(source, index, out, fps, dataset, checkpoint)
        return
    if not (source / "dataset.json").is_file():
        raise ConfigError(f"{source} is not a dataset directory (no dataset.json) nor a run directory (no run.json)")
    ds = Dataset.open(source)
    if not len(ds):
        raise ConfigError(f"{source} has no accepted trajectories to render")
    position = 0 if index is None else ds.position(index)
    traj = ds[position]
    path = out or source / f"render_{int(ds.indices[position]):06d}.mp4"
    render_video(load_robot(robot or traj.robot), traj.qpos, path, fps=fps, scene=traj.scene, prop_poses=traj.prop_poses)
    console.print(f"wrote {path} ({traj.duration:.1f} s of motion)")


def _render_run(run: Path, index: int | None, out: Path | None, fps: int, dataset: Path | None,
                checkpoint: Path | None = None) -> None:
    from opt2skill.eval.evaluate import EvalRequest, evaluate, load_run_policy
    from opt2skill.eval.render import render_video

    policy = load_run_policy(run, checkpoint)
    requests = [EvalRequest(run=run, dataset=dataset, n=1, indices=(index,))] if index is not None else [
        EvalRequest(run=run, dataset=dataset, n=1), EvalRequest(run=run, dataset=dataset, n=1, split="all")]
    for i, request in enumerate(requests):
        try:
            report, rollouts = evaluate(request, progress=False, run=policy)
            break
        except DataError:
            if i + 1 == len(requests):
                raise
    r, result = rollouts[0], report.results[0]
    path = out or Path(run) / f"render_{result.index:06d}.mp4"
    render_video(policy.robot, r.tracked.qpos, path, ghost_qpos=r.reference.qpos, fps=fps, scene=r.reference.scene,
                 prop_poses=r.tracked.prop_poses)
    console.print(f"wrote {path}: {report.title()} tracking reference #{result.index} ({report.references['note']}); "
                  f"{r.duration:.1f} of {r.reference.duration:.1f} s tracked ({result.cause}); ghost: the reference")
