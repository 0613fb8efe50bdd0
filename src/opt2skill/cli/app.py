"""Entry point: `opt2skill <command>`. User errors print one line and exit with status 2."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import typer

from opt2skill.cli import data, experiment, render, retarget, robot, train
from opt2skill.cli import eval as evaluation
from opt2skill.cli.console import err_console
from opt2skill.errors import DataWarning, Opt2SkillError

app = typer.Typer(
    help="Opt2Skill: trajectory optimization to robust humanoid skills.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.add_typer(robot.app, name="robot")
app.add_typer(data.app)  # generate, validate, inspect
app.add_typer(retarget.app)  # retarget
app.add_typer(render.app)  # render
app.add_typer(train.app)  # train, play
app.add_typer(evaluation.app)  # eval, compare, sweep, export, deploy-sim
app.add_typer(experiment.app, name="experiment")  # table3


@app.command()
def demo(
    out: Path = typer.Option(Path("demo"), help="Where every output goes (rerunning resumes)."),
    robot_name: str = typer.Option("digit", "--robot", help="Built-in robot name, or path to a robot.yaml."),
    task: str = typer.Option("walk", help="Task of the references."),
    n_train: int = typer.Option(3, "--n-train", help="Training references."),
    n_test: int = typer.Option(2, "--n-test", help="Held-out references (another seed)."),
    train_steps: int = typer.Option(30_000, "--train-steps", help="PPO environment steps."),
    init: str = typer.Option("distill", "--init", help="distill: distil the optimizer's feedback expert, then PPO; "
                             "scratch: PPO alone."),
    distill_steps: int = typer.Option(60_000, "--distill-steps", help="Environment steps of distillation."),
    num_envs: int = typer.Option(32, "--num-envs", help="Simulated worlds while training."),
    workers: int = typer.Option(0, min=0, help="Generation processes (0: every core)."),
    fps: int = typer.Option(20, min=1, max=60, help="Frames per second of the video."),
) -> None:
    """The whole pipeline, small and fast: references, training, evaluation, ONNX, 2 kHz player, video."""
    from opt2skill.cli.demo import DemoSettings, run_demo

    run_demo(DemoSettings(out=out, robot=robot_name, task=task, n_train=n_train, n_test=n_test,
                          train_steps=train_steps, init=init, distill_steps=distill_steps, num_envs=num_envs,
                          workers=workers, fps=fps))


def _show_data_warnings() -> None:
    """DataWarnings (a skipped file, a lock taken over) as one line each, like errors."""
    default = warnings.showwarning
    if getattr(default, "shows_data_warnings", False):  # installed already (main called again in-process)
        return

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, DataWarning):
            err_console.print(f"[bold yellow]warning:[/] {message}", highlight=False, soft_wrap=True)
        else:
            default(message, category, filename, lineno, file, line)

    show.shows_data_warnings = True
    warnings.showwarning = show
    warnings.simplefilter("always", DataWarning)


def main() -> None:
    _show_data_warnings()
    try:
        app()
    except Opt2SkillError as exc:
        err_console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except KeyboardInterrupt:
        err_console.print("interrupted")
        sys.exit(130)
