"""`opt2skill robot ...`: list robots, and check a model in MuJoCo and Pinocchio."""

from __future__ import annotations

import typer

from opt2skill.cli.console import console, figures_table
from opt2skill.robots import DEFAULT_ROBOT, available_robots

app = typer.Typer(help="List robots and check a robot model.", no_args_is_help=True)


@app.command("list")
def list_robots() -> None:
    """Built-in robots."""
    for name in available_robots():
        console.print(name)


@app.command("check")
def check(
    robot: str = typer.Option(DEFAULT_ROBOT, help="Built-in robot name, or path to a robot.yaml."),
    samples: int = typer.Option(100, min=1, help="Random states for the MuJoCo/Pinocchio comparison."),
    seed: int = typer.Option(0, help="Seed of the random states."),
    seconds: float = typer.Option(5.0, min=0.1, max=600.0, help="Standing test duration (s)."),
) -> None:
    """Compare MuJoCo and Pinocchio at random states, then hold the robot standing in MuJoCo."""
    from opt2skill.model import load_robot
    from opt2skill.model.check import compare

    loaded = load_robot(robot)
    agreement = compare(loaded, n=samples, seed=seed)
    console.print(
        figures_table(
            f"{loaded.name}: MuJoCo vs Pinocchio, largest difference over {samples} random states",
            [
                ("site positions (m)", f"{agreement.site_position:.1e}"),
                ("site rotations", f"{agreement.site_rotation:.1e}"),
                ("mass matrix, armature included", f"{agreement.mass_matrix:.1e}"),
                ("gravity torques (N m)", f"{agreement.gravity:.1e}"),
                ("gravity + Coriolis (N m)", f"{agreement.bias:.1e}"),
                ("foot and hand Jacobians", f"{agreement.jacobian:.1e}"),
                ("(largest Coriolis term compared, N m)", f"{agreement.largest_coriolis:.1f}"),
            ],
        )
    )
    print_standing(loaded, seconds)


def print_standing(loaded, seconds: float) -> None:
    from opt2skill.model.standing import simulate_standing

    report = simulate_standing(loaded, seconds=seconds)
    console.print(
        figures_table(
            f"{loaded.name}: standing {seconds:g} s in MuJoCo, PD at the default pose + gravity feedforward",
            [
                ("max tilt (deg)", f"{report.max_tilt_deg:.3f}"),
                ("max base drift (mm)", f"{1e3 * report.max_base_drift_m:.2f}"),
                ("max foot slip (mm)", f"{1e3 * report.max_foot_slip_m:.2f}"),
                ("final base height (m)", f"{report.final_base_height_m:.4f}"),
                ("knee feedforward L/R (N m)", "{:.1f} / {:.1f}".format(*report.feedforward_knee_nm)),
                ("max |torque| / limit", f"{report.max_torque_ratio:.2f}"),
                ("fell", "yes" if report.fell else "no"),
            ],
        )
    )
    if report.fell:
        raise typer.Exit(1)
