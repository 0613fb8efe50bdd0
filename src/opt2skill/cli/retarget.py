"""`opt2skill retarget FILE... --out DIR`: human motion (BVH, AMASS .npz) to Digit references."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import typer

from opt2skill.cli.console import console

app = typer.Typer()


@app.command()
def retarget(
    files: list[Path] = typer.Argument(..., help="Motion files: .bvh (BVH) or .npz (AMASS-style SMPL/SMPL-H)."),
    out: Path = typer.Option(..., help="Dataset directory (resumable: rerun the same command to continue)."),
    robot: str = typer.Option("digit", help="Built-in robot name, or path to a robot.yaml."),
    format_: str = typer.Option("auto", "--format", help="auto (by suffix), bvh or smpl."),
    up: str = typer.Option(None, help="The files' up axis, y or z (default: y for BVH, z for AMASS)."),
    unit: float = typer.Option(None, help="BVH: metres per file unit (default: 0.01 for skeletons over 10 units tall)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
) -> None:
    """Retarget human walking clips to the robot: calibrate, scale, QP IK, filter, write records."""
    from opt2skill.retarget.batch import retarget_files

    summary = retarget_files(list(files), out, robot, format_, up, unit, shlex.join(["opt2skill", *sys.argv[1:]]),
                             progress=not quiet, log=lambda line: console.print(line, highlight=False, soft_wrap=True))
    counts = summary["counts"]
    console.print(f"{out}: {counts.get('accepted', 0)} accepted, {counts.get('rejected', 0)} rejected, "
                  f"{counts.get('failed', 0)} failed of {summary['requested']} clips", highlight=False)
    if counts.get("failed", 0):
        raise typer.Exit(1)
