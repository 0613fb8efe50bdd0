"""Robot configuration as data: one YAML file per robot beside its MJCF.

Adding a humanoid means adding a folder with `robot.yaml` and its MJCF (docs/robots.md); no code
changes. Everything here is validated on load, and every problem is reported with the file and key.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from opt2skill.errors import ConfigError
from opt2skill.yaml_files import read_mapping


@dataclass(frozen=True)
class JointConfig:
    """One actuated joint: PD gains (N m/rad, N m s/rad) and limits (N m, rad/s)."""

    name: str
    kp: float
    kd: float
    torque_limit: float
    velocity_limit: float
    default: float


@dataclass(frozen=True)
class FootConfig:
    """A foot that makes flat (6D) contact: its body, sole-centre site, corner sites and sole size."""

    name: str
    body: str
    sole_site: str
    corner_sites: tuple[str, ...]
    half_length: float
    half_width: float


@dataclass(frozen=True)
class RobotConfig:
    name: str
    directory: Path
    mjcf_path: Path
    root_joint: str
    base_body: str
    imu_site: str
    stand_keyframe: str
    friction_coefficient: float
    joints: tuple[JointConfig, ...]
    joint_groups: dict[str, tuple[str, ...]]
    end_effectors: dict[str, str]
    feet: tuple[FootConfig, ...]
    hands: tuple[str, ...]
    source_hash: str

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def num_joints(self) -> int:
        return len(self.joints)

    @property
    def kp(self) -> np.ndarray:
        return np.array([j.kp for j in self.joints])

    @property
    def kd(self) -> np.ndarray:
        return np.array([j.kd for j in self.joints])

    @property
    def torque_limit(self) -> np.ndarray:
        return np.array([j.torque_limit for j in self.joints])

    @property
    def velocity_limit(self) -> np.ndarray:
        return np.array([j.velocity_limit for j in self.joints])

    @property
    def default_pose(self) -> np.ndarray:
        return np.array([j.default for j in self.joints])

    def group_indices(self, group: str) -> np.ndarray:
        """Indices (into the actuated joints) of a named joint group."""
        if group not in self.joint_groups:
            raise ConfigError(
                f"robot '{self.name}' has no joint group '{group}'; groups: {', '.join(self.joint_groups)}"
            )
        names = self.joint_names
        return np.array([names.index(j) for j in self.joint_groups[group]])


_TOP_KEYS = {
    "name", "mjcf", "root_joint", "base_body", "imu_site", "stand_keyframe", "friction_coefficient",
    "joints", "joint_groups", "default_pose", "end_effectors", "feet", "hands",
}
_JOINT_KEYS = {"kp", "kd", "torque_limit", "velocity_limit"}
_FOOT_KEYS = {"body", "sole_site", "corner_sites", "half_length", "half_width"}


def load_robot_config(path: Path) -> RobotConfig:
    """Parse and check a robot.yaml. Model-dependent checks happen when the model is loaded."""
    path = Path(path)
    raw = read_mapping(path, "robot config")
    where = str(path)
    _check_keys(raw, _TOP_KEYS, _TOP_KEYS - {"default_pose"}, where)

    mjcf_path = (path.parent / str(raw["mjcf"])).resolve()
    if not mjcf_path.is_file():
        raise ConfigError(f"{where}: mjcf file '{raw['mjcf']}' not found (looked for {mjcf_path})")

    joints_raw = _mapping(raw["joints"], f"{where}: joints")
    default_pose = _mapping(raw.get("default_pose") or {}, f"{where}: default_pose")
    unknown = set(default_pose) - set(joints_raw)
    if unknown:
        raise ConfigError(f"{where}: default_pose names joints not in 'joints': {sorted(unknown)}")
    joints = []
    for name, spec in joints_raw.items():
        spec = _mapping(spec, f"{where}: joints.{name}")
        _check_keys(spec, _JOINT_KEYS, _JOINT_KEYS, f"{where}: joints.{name}")
        values = {k: _positive(spec[k], f"{where}: joints.{name}.{k}") for k in _JOINT_KEYS}
        joints.append(JointConfig(name=name, default=float(default_pose.get(name, 0.0)), **values))

    names = [j.name for j in joints]
    groups = {}
    for group, members in _mapping(raw["joint_groups"], f"{where}: joint_groups").items():
        members = tuple(members or ())
        missing = [m for m in members if m not in names]
        if missing:
            raise ConfigError(f"{where}: joint group '{group}' names unknown joints {missing}")
        groups[group] = members

    end_effectors = {str(k): str(v) for k, v in _mapping(raw["end_effectors"], f"{where}: end_effectors").items()}
    feet = []
    for name, spec in _mapping(raw["feet"], f"{where}: feet").items():
        spec = _mapping(spec, f"{where}: feet.{name}")
        _check_keys(spec, _FOOT_KEYS, _FOOT_KEYS, f"{where}: feet.{name}")
        if name not in end_effectors:
            raise ConfigError(f"{where}: foot '{name}' must also be listed in end_effectors")
        feet.append(
            FootConfig(
                name=name,
                body=str(spec["body"]),
                sole_site=str(spec["sole_site"]),
                corner_sites=tuple(spec["corner_sites"]),
                half_length=_positive(spec["half_length"], f"{where}: feet.{name}.half_length"),
                half_width=_positive(spec["half_width"], f"{where}: feet.{name}.half_width"),
            )
        )
    hands = tuple(raw["hands"] or ())
    bad = [h for h in hands if h not in end_effectors]
    if bad:
        raise ConfigError(f"{where}: hands {bad} must also be listed in end_effectors")
    mu = _positive(raw["friction_coefficient"], f"{where}: friction_coefficient")

    digest = hashlib.sha256(path.read_bytes() + mjcf_path.read_bytes()).hexdigest()
    return RobotConfig(
        name=str(raw["name"]),
        directory=path.parent.resolve(),
        mjcf_path=mjcf_path,
        root_joint=str(raw["root_joint"]),
        base_body=str(raw["base_body"]),
        imu_site=str(raw["imu_site"]),
        stand_keyframe=str(raw["stand_keyframe"]),
        friction_coefficient=mu,
        joints=tuple(joints),
        joint_groups=groups,
        end_effectors=end_effectors,
        feet=tuple(feet),
        hands=hands,
        source_hash=digest,
    )


def _mapping(value: Any, where: str) -> dict:
    if not isinstance(value, dict):
        raise ConfigError(f"{where} must be a mapping, got {type(value).__name__}")
    return value


def _check_keys(raw: dict, allowed: set[str], required: set[str], where: str) -> None:
    unknown = set(raw) - allowed
    if unknown:
        raise ConfigError(f"{where}: unknown keys {sorted(unknown)}; allowed: {sorted(allowed)}")
    missing = required - set(raw)
    if missing:
        raise ConfigError(f"{where}: missing keys {sorted(missing)}")


def _positive(value: Any, where: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{where} must be a number, got {value!r}") from None
    if not np.isfinite(number) or number <= 0:
        raise ConfigError(f"{where} must be a positive finite number, got {value!r}")
    return number
