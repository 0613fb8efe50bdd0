"""`opt2skill generate | validate | inspect`: build a reference dataset, re-check it, plot from it."""

from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path

import typer

from opt2skill.cli.console import console
from opt2skill.cli.option_help import limit_help, set_help
from opt2skill.errors import ConfigError
from opt2skill.output_paths import check_output_file

app = typer.Typer()


def _pairs(items: list[str], option: str, form: str) -> dict[str, str]:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip() or not value.strip():
            raise ConfigError(f"{option} expects {form}, got '{item}'")
        out[name.strip()] = value.strip()
    return out


def _ranges(items: list[str]) -> dict[str, tuple[float, float]]:
    ranges = {}
    for name, text in _pairs(items, "--set", "name=lo:hi or name=value").items():
        parts = text.split(":")
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise ConfigError(f"--set {name}={text}: expected numbers as lo:hi or a single value") from None
        if len(values) not in (1, 2):
            raise ConfigError(f"--set {name}={text}: expected lo:hi or a single value")
        ranges[name] = (values[0], values[-1])
    return ranges


def _config(items: list[str]) -> dict[str, object]:
    """--config key=value pairs, each value a number, true/false or text (the task config checks it)."""
    from opt2skill.trajopt.config import parse_value

    return {key: parse_value(text) for key, text in _pairs(items, "--config", "key=value (a dotted task config key)").items()}


@app.command()
def generate(
    task: str = typer.Argument(..., help="Task name (e.g. walk, squat)."),
    n: int = typer.Option(20, "--n", help="Number of trajectories (indices 0 .. n-1)."),
    seed: int = typer.Option(0, help="Dataset seed: parameters of trajectory i depend only on (seed, i)."),
    workers: int = typer.Option(0, min=0, help="Parallel solves (0: every CPU, or the Ray cluster's CPUs)."),
    out: Path = typer.Option(None, help="Dataset directory (default: data/TASK)."),
    robot: str = typer.Option("digit", help="Built-in robot name, or path to a robot.yaml."),
    ray: bool = typer.Option(False, "--ray", help="Run each trajectory as a Ray task."),
    address: str = typer.Option(None, help="Ray cluster address (with --ray); default: start a local instance."),
    set_: list[str] = typer.Option([], "--set", help=set_help()),
    limit: list[str] = typer.Option([], "--limit", help=limit_help()),
    config: list[str] = typer.Option([], "--config", help=(
        "Task config override, key=value with a dotted key (repeatable), e.g. solver.reg_increase_below=0.2 "
        "or receding.window=2.0; part of the dataset's identity.")),
    keep_gains: bool = typer.Option(False, "--keep-gains", help="Store the solver's feedback gains (float32) with the knots."),
    retry_failed: bool = typer.Option(False, "--retry-failed", help="Solve again the indices whose solve failed."),
    timeout: float = typer.Option(None, help="Seconds allowed per trajectory (default: no limit)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
) -> None:
    """Solve and validate N trajectories of TASK into an HDF5 dataset; resumes where it stopped."""
    os.environ["OMP_NUM_THREADS"] = "1"  # before Crocoddyl loads, here and in every worker
    from opt2skill.cli.data_report import print_generation
    from opt2skill.trajopt.generate import GenerateRequest
    from opt2skill.trajopt.generate import generate as run

    if address and not ray:
        raise ConfigError("--address needs --ray")
    request = GenerateRequest(
        task=task, n=n, seed=seed, out=out or Path("data") / task, robot=robot, workers=workers,
        ranges=_ranges(set_), limits=_pairs(limit, "--limit", "name=value"), keep_gains=keep_gains,
        retry_failed=retry_failed, timeout=timeout, ray=ray, ray_address=address, task_config=_config(config),
        command=shlex.join(["opt2skill", *sys.argv[1:]]),
    )
    summary = run(request, progress=not quiet)
    print_generation(summary, request.out)
    if summary["requested"] > n:  # a smaller --n removes nothing: say so rather than ignore it
        console.print(f"note: {request.out} already holds indices up to {summary['requested'] - 1}; --n {n} is "
                      f"smaller, so nothing was removed (the dataset keeps all {summary['requested']}; use another "
                      "--out for a smaller one)", highlight=False, soft_wrap=True)


@app.command()
def validate(
    directory: Path = typer.Argument(..., help="Dataset directory."),
    workers: int = typer.Option(0, min=0, help="Parallel processes (0: every CPU)."),
    robot: str = typer.Option(None, help="Robot name or robot.yaml path (default: the dataset's robot)."),
    limit: list[str] = typer.Option([], "--limit", help=limit_help("Judge with another limit")),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
) -> None:
    """Recompute every trajectory's validation from the stored data and compare with the stored figures."""
    os.environ["OMP_NUM_THREADS"] = "1"
    from opt2skill.cli.data_report import print_revalidation
    from opt2skill.trajopt.revalidate import revalidate

    report = revalidate(directory, workers=workers or (os.cpu_count() or 1), robot=robot,
                        limits=_pairs(limit, "--limit", "name=value"), progress=not quiet)
    print_revalidation(report, directory)
    if report.bad_files is not None:
        raise report.bad_files.error()
    if report.disagreements:
        raise typer.Exit(1)


@app.command()
def inspect(
    directory: Path = typer.Argument(..., help="Dataset directory."),
    index: int = typer.Option(None, help="Trajectory index (as generated); default: the first stored."),
    out: Path = typer.Option(None, help="PNG file, or a folder for inspect_INDEX.png (default: DIR/inspect_INDEX.png)."),
    rejected: bool = typer.Option(False, "--rejected", help="Look among the rejected trajectories."),
) -> None:
    """Plot one trajectory: base and foot paths, heights, joint torques, contact forces and schedule."""
    from opt2skill.data.plot import plot_trajectory
    from opt2skill.data.reader import Dataset
    from opt2skill.data.store import ACCEPTED, REJECTED

    ds = Dataset.open(directory, status=REJECTED if rejected else ACCEPTED)
    if not len(ds):
        raise ConfigError(f"{directory} has no {'rejected' if rejected else 'accepted'} trajectories")
    position = 0 if index is None else ds.position(index)
    index = int(ds.indices[position])
    name = f"inspect_{index:06d}.png"
    path = Path(out) / name if out is not None and Path(out).is_dir() else (out or Path(directory) / name)
    check_output_file(path, suffix=".png")
    from opt2skill.robots import find_robot_config

    traj = ds[position]
    try:
        config = find_robot_config(traj.robot)
    except ConfigError:  # a robot given by path when generating: plot without joint names
        config = None
    plot_trajectory(traj, path, title=f"{directory} #{index}", robot_config=config)
    console.print(f"wrote {path}")
