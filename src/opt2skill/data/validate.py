"""Validation of a trajectory: every figure measured, compared with its limit, stored with it.

`validate(robot, traj, config, task_errors)` returns the `validation` dict of the record:

    {"accepted": bool, "reasons": [figures over their limit], "figures": {name: value},
     "limits": {name: limit}, "replay_windows": [[start s, fall time s or None], ...], "time": s}

A kinematic record (`traj.has_dynamics` False: IK or retargeted references) is judged on the
kinematic figures only (`figures.KINEMATIC`: limits, slip, ground penetration, derived fields); the
result then also holds `kinematic_only: True`, `skipped` (the figures not measured) and a `note`.

A figure fails when it is not finite or exceeds its limit; a limit of None reports the figure
without judging it. Figures and default limits are listed in `FIGURES` and docs/data.md. Task
errors (e.g. realized vs requested speed) come from the task, with the task's own limits.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from opt2skill.data import checks
from opt2skill.data.figures import FIGURES, KINEMATIC, Figure  # noqa: F401  (Figure: part of this module's API)
from opt2skill.data.record import Trajectory
from opt2skill.data.replay import Replayer, ReplaySettings
from opt2skill.errors import ConfigError, DataError
from opt2skill.model.robot import Robot


@dataclass(frozen=True)
class ValidationConfig:
    limits: dict[str, float | None] = field(default_factory=lambda: {n: f.limit for n, f in FIGURES.items()})
    replay: ReplaySettings = ReplaySettings()
    cop_min_force: float = 20.0  # N: the CoP of a sole is checked where its normal force exceeds this

    def with_overrides(self, overrides: dict[str, str | float | None]) -> ValidationConfig:
        """`{"foot_slip": 3, "replay.window": 1.5, "cop_violation": "none", "cop_min_force": 10}`."""
        limits, replay, cop_min_force = dict(self.limits), asdict(self.replay), self.cop_min_force
        for name, raw in overrides.items():
            if name == "cop_min_force":
                cop_min_force = _parse_value(name, raw, float)
            elif name.startswith("replay."):
                key = name.removeprefix("replay.")
                if key not in replay:
                    raise ConfigError(f"unknown replay setting '{key}'; settings: {', '.join(replay)}")
                replay[key] = _parse_value(name, raw, type(replay[key]))
            elif name in limits:
                limits[name] = None if str(raw).lower() == "none" else _parse_value(name, raw, float)
                if limits[name] is not None and limits[name] < 0:
                    raise ConfigError(f"limit '{name}' must be >= 0 or 'none', got {raw}")
            else:
                raise ConfigError(
                    f"unknown validation limit '{name}'; limits: {', '.join(limits)}; settings: cop_min_force, "
                    + ", ".join(f"replay.{k}" for k in replay)
                )
        return replace(self, limits=limits, replay=ReplaySettings(**replay), cop_min_force=cop_min_force)

    def as_dict(self) -> dict[str, Any]:
        return {"limits": dict(self.limits), "replay": asdict(self.replay), "cop_min_force": self.cop_min_force}

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> ValidationConfig:
        try:
            return cls(limits={**cls().limits, **raw["limits"]}, replay=ReplaySettings(**raw["replay"]),
                       cop_min_force=float(raw["cop_min_force"]))
        except (KeyError, TypeError) as exc:
            raise DataError(f"malformed validation settings {raw!r} ({exc})") from None


def _parse_value(name: str, raw: Any, kind: type) -> Any:
    if kind is bool:
        text = str(raw).lower()
        if text not in ("true", "false", "1", "0"):
            raise ConfigError(f"'{name}' must be true or false, got {raw}")
        return text in ("true", "1")
    try:
        value = kind(raw)
    except (TypeError, ValueError):
        raise ConfigError(f"'{name}' must be a number, got {raw!r}") from None
    if not math.isfinite(value):
        raise ConfigError(f"'{name}' must be finite, got {raw}")
    return value


def _residual_stats(residual: np.ndarray, prefix: str) -> dict[str, float]:
    if residual.size == 0:
        return {}
    return {f"{prefix}_max": float(np.abs(residual).max()), f"{prefix}_rms": float(np.sqrt(np.mean(residual**2)))}


def knot_residuals(robot: Robot, traj: Trajectory) -> dict[str, float]:
    """Residuals on the solver grid when the record stores it (knots x, u, contact_force, dt)."""
    k = traj.knots
    if not all(name in k for name in ("x", "u", "contact_force", "dt")):
        return {}
    nq = robot.pin_model.nq
    x, dt = np.asarray(k["x"], dtype=float), np.asarray(k["dt"], dtype=float)
    res = checks.dynamics_residual(
        robot, x[:-1, :nq], x[:-1, nq:], x[1:, nq:], dt, k["u"], k["contact_force"], traj.contact_names
    )
    impulse = dt == 0
    out = _residual_stats(res[~impulse], "id_residual_knots")
    if impulse.any():
        out["impulse_residual_max"] = float(np.abs(res[impulse]).max())
    return out


def physical_figures(robot: Robot, traj: Trajectory, config: ValidationConfig) -> dict[str, float | None]:
    """Every figure except the replay and the task errors."""
    figures: dict[str, float | None] = {"dynamic_gap": traj.solver.get("dynamic_gap")}
    figures.update(knot_residuals(robot, traj))
    frame_res = checks.frame_dynamics_residual(robot, traj)
    figures.update(_residual_stats(frame_res[~checks.touchdown_frames(traj.contact_active)], "id_residual_frames"))
    poses = checks.foot_site_poses(robot, traj)  # the soles' kinematics once for the checks that need them
    figures.update(checks.contact_violations(robot, traj, config.cop_min_force, poses))
    figures.update(checks.limit_violations(robot, traj))
    figures["foot_slip"] = 1e3 * checks.foot_slip(robot, traj, poses)
    figures["derived_fields_error"] = checks.derived_fields_error(robot, traj)
    return figures


def kinematic_figures(robot: Robot, traj: Trajectory) -> dict[str, float | None]:
    """The figures of a record without dynamics: joint and speed limits, slip, penetration, derived fields."""
    limits = checks.limit_violations(robot, traj)
    poses = checks.foot_site_poses(robot, traj)
    return {
        "joint_limit_violation": limits["joint_limit_violation"],
        "velocity_violation": limits["velocity_violation"],
        "foot_slip": 1e3 * checks.foot_slip(robot, traj, poses),
        "foot_penetration": 1e3 * checks.foot_penetration(robot, traj, poses),
        "derived_fields_error": checks.derived_fields_error(robot, traj),
    }


def replay_figures(robot: Robot, traj: Trajectory, settings: ReplaySettings) -> tuple[dict[str, float | None], list]:
    replayer = Replayer(robot, traj, settings, all_sensors=False)
    windows = replayer.windows()
    full = replayer.full()
    figures = {
        "replay_fallen_windows": sum(w.fall_time is not None for w in windows) / len(windows),
        "replay_joint_rms": max(w.joint_rms for w in windows),
        "replay_base_error": max(w.base_error for w in windows),
        "replay_foot_error": 100.0 * max(w.foot_error for w in windows),
        "replay_fall_time": full.fall_time,
    }
    feedback = replayer.feedback()
    if feedback is not None:
        figures.update(
            replay_feedback_fallen=float(feedback.fall_time is not None),
            replay_feedback_fall_time=feedback.fall_time,
            replay_feedback_base_error=feedback.base_error,
            replay_feedback_foot_error=100.0 * feedback.foot_error,
        )
    return figures, [[w.start, w.fall_time] for w in windows]


def judge(figures: dict[str, float | None], limits: dict[str, float | None]) -> list[str]:
    """Names of the figures that fail: not finite, or above their limit."""
    reasons = []
    for name, limit in limits.items():
        value = figures.get(name)
        if limit is None or value is None:
            continue
        if not math.isfinite(value) or value > limit:
            reasons.append(name)
    return reasons


def validate(
    robot: Robot,
    traj: Trajectory,
    config: ValidationConfig = ValidationConfig(),
    task_errors: dict[str, dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """Measure every figure of `traj` and decide; the result is stored as the record's `validation`."""
    if traj.robot != robot.name:
        raise DataError(f"trajectory is for robot '{traj.robot}', not '{robot.name}'")
    start = time.perf_counter()
    skipped: list[str] = []
    if traj.has_dynamics:
        figures = physical_figures(robot, traj, config)
        replay, windows = replay_figures(robot, traj, config.replay)
        figures.update(replay)
    else:  # no torques or contact forces to check, nothing to replay them with
        figures, windows = kinematic_figures(robot, traj), []
        skipped = [name for name in FIGURES if name not in KINEMATIC]
    limits = dict(config.limits)
    units = {name: FIGURES[name].unit for name in figures}
    for name, err in (task_errors or {}).items():
        key = f"task.{name}"
        figures[key] = float(err["value"])
        limits[key] = None if err.get("limit") is None else float(err["limit"])
        units[key] = str(err.get("unit", ""))
    reasons = judge(figures, limits)
    out = {
        "accepted": not reasons,
        "reasons": reasons,
        "figures": figures,
        "limits": {name: limits.get(name) for name in figures},
        "units": units,
        "replay_windows": windows,
        "time": time.perf_counter() - start,
    }
    if skipped:
        out["kinematic_only"] = True
        out["skipped"] = skipped
        out["note"] = (f"kinematic record (source '{traj.source}', has_dynamics=False): no torques or contact forces; "
                       f"dynamics and replay checks skipped ({len(skipped)} figures)")
    return out
