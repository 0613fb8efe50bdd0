"""Entry point: `opt2skill <command>`. User errors print one line and exit with status 2."""

from __future__ import annotations

import sys

import typer

from opt2skill.cli import data, render, robot
from opt2skill.cli.console import err_console
from opt2skill.errors import Opt2SkillError

app = typer.Typer(
    help="Opt2Skill: trajectory optimization to robust humanoid skills.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.add_typer(robot.app, name="robot")
app.add_typer(data.app)  # generate, validate, inspect
app.add_typer(render.app)  # render


@app.command()
def demo(
    robot_name: str = typer.Option("digit", "--robot", help="Built-in robot name, or path to a robot.yaml."),
) -> None:
    """Run the main job on the built-in defaults (for now: load the robot and hold it standing 5 s)."""
    from opt2skill.model import load_robot

    loaded = load_robot(robot_name)
    robot.print_standing(loaded, seconds=5.0)


def main() -> None:
    try:
        app()
    except Opt2SkillError as exc:
        err_console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except KeyboardInterrupt:
        err_console.print("interrupted")
        sys.exit(130)
