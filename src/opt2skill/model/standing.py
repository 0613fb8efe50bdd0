"""Hold the robot standing in MuJoCo with PD plus gravity-compensation feedforward, and measure it.

The first sign of life of a new robot model: if this falls, nothing downstream can work.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import mujoco
import numpy as np

from opt2skill.geometry import tilt_angle
from opt2skill.model.robot import Robot
from opt2skill.model.statics import gravity_compensation


@dataclass(frozen=True)
class StandingReport:
    seconds: float
    max_tilt_deg: float
    max_base_drift_m: float  # largest distance of the base from its start position
    max_foot_slip_m: float  # largest horizontal sole displacement
    final_base_height_m: float
    max_torque_ratio: float  # largest |u| / torque limit
    feedforward_knee_nm: tuple[float, float]
    fell: bool

    def as_dict(self) -> dict:
        return asdict(self)


def feedforward_ctrl(robot: Robot, qpos: np.ndarray, torque: np.ndarray) -> np.ndarray:
    """PD targets that add a feedforward torque: kp (q* + u/kp - q) - kd qd = kp (q* - q) - kd qd + u."""
    cfg = robot.config
    return cfg.default_pose + torque / cfg.kp


def simulate_standing(robot: Robot, seconds: float = 5.0, feedforward: bool = True) -> StandingReport:
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = robot.stand_qpos
    mujoco.mj_forward(m, d)
    balance = gravity_compensation(robot, robot.stand_qpos)
    torque = balance.torque if feedforward else np.zeros(m.nu)
    d.ctrl[:] = feedforward_ctrl(robot, d.qpos, torque)

    soles = [robot.site_id(f.sole_site) for f in robot.config.feet]
    base0, soles0 = d.qpos[:3].copy(), d.site_xpos[soles, :2].copy()
    limit = robot.config.torque_limit
    max_tilt = max_drift = max_slip = max_ratio = 0.0
    for _ in range(int(round(seconds / m.opt.timestep))):
        mujoco.mj_step(m, d)
        max_tilt = max(max_tilt, float(tilt_angle(d.qpos[3:7])))
        max_drift = max(max_drift, float(np.linalg.norm(d.qpos[:3] - base0)))
        max_slip = max(max_slip, float(np.linalg.norm(d.site_xpos[soles, :2] - soles0, axis=1).max()))
        max_ratio = max(max_ratio, float(np.abs(d.actuator_force / limit).max()))
    knees = [robot.config.joint_names.index(j) for j in robot.config.joint_names if j.endswith("knee")]
    return StandingReport(
        seconds=seconds,
        max_tilt_deg=float(np.degrees(max_tilt)),
        max_base_drift_m=max_drift,
        max_foot_slip_m=max_slip,
        final_base_height_m=float(d.qpos[2]),
        max_torque_ratio=max_ratio,
        feedforward_knee_nm=tuple(float(torque[k]) for k in knees[:2]),
        fell=bool(np.degrees(max_tilt) > 30.0 or d.qpos[2] < 0.5 * base0[2]),
    )
