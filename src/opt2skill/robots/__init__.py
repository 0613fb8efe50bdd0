"""Robot descriptions shipped with the package, found by name, or a user's robot.yaml by path."""

from __future__ import annotations

from pathlib import Path

from opt2skill.errors import ConfigError
from opt2skill.robots.config import FootConfig, JointConfig, RobotConfig, load_robot_config

ROBOTS_DIR = Path(__file__).parent
DEFAULT_ROBOT = "digit"


def available_robots() -> list[str]:
    return sorted(p.parent.name for p in ROBOTS_DIR.glob("*/robot.yaml"))


def find_robot_config(name_or_path: str | Path = DEFAULT_ROBOT) -> RobotConfig:
    """A built-in robot by name (e.g. 'digit'), or a robot.yaml (or its folder) by path."""
    candidate = Path(name_or_path)
    if candidate.suffix in (".yaml", ".yml"):
        return load_robot_config(candidate)
    if candidate.is_dir() and (candidate / "robot.yaml").is_file():
        return load_robot_config(candidate / "robot.yaml")
    builtin = ROBOTS_DIR / str(name_or_path) / "robot.yaml"
    if builtin.is_file():
        return load_robot_config(builtin)
    raise ConfigError(
        f"unknown robot '{name_or_path}'; built-in robots: {', '.join(available_robots())}, "
        "or give the path of a robot.yaml"
    )


__all__ = [
    "DEFAULT_ROBOT", "FootConfig", "JointConfig", "RobotConfig", "available_robots", "find_robot_config",
    "load_robot_config",
]
