"""Human motion to a Digit reference: calibrate, scale, keypoints, QP IK, filter, record.

1. Resample the joint positions to 200 Hz, put the floor at z = 0 (the lowest ankle height of the
   clip is the standing ankle height), and turn the clip about z so that it walks along +x.
2. Calibrate to Digit: the leg ratio s = Digit's hip height / the human's (hip joint above the
   floor, 90th percentile over the clip: the leg near full stance). Torso and feet positions are
   scaled by s about the start, so the torso speed is scaled by the leg ratio (the paper's
   "scale the torso speeds to match the new leg length"); the feet keep Digit's stance width
   (their mean lateral offset from the pelvis is replaced by the stand pose's); the hands keep
   their motion about the shoulders, scaled by the arm ratio.
3. Keypoints: soles (midway between ankle and toe, flat, yawed along the foot), torso (pelvis
   position and heading from the hip line, upright), hands relative to the torso.
   A foot is in stance where its sole is below `contact_height` and slower than `contact_speed`;
   a stance sole is held where the stance began, on the floor (no slip, no penetration).
4. QP IK to Digit (`baselines.ik_solver`), 5. filter, 6. write the record (`has_dynamics=False`).

Filters (the paper's human dataset, Sec. IV-B): forward walking (mean lateral speed under
`max_lateral_ratio` of the forward speed), torso speed in [0, 1.5] m/s after scaling, foot
clearance (median swing apex) in [0.10, 0.20] m, feet reached by the IK within 5 mm. They enter
the validation as task figures, so a rejected clip carries its reasons like any record.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from opt2skill.baselines.ik_solver import FEET, FrameTargets, IKSettings, KeypointIK
from opt2skill.baselines.kinematic_record import kinematic_trajectory
from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.errors import DataError
from opt2skill.model.robot import Robot
from opt2skill.provenance import provenance
from opt2skill.retarget.motion import HumanMotion
from opt2skill.tasks.walk_human import INFO
from opt2skill.trajopt.skills.gait import yaw_matrix

TASK = INFO.name
SIDES = {"left_foot": "left", "right_foot": "right"}


@dataclass(frozen=True)
class RetargetSettings:
    speed_range: tuple[float, float] = (0.0, 1.5)  # m/s, mean forward torso speed after scaling
    clearance_range: tuple[float, float] = (0.10, 0.20)  # m, median swing apex after scaling
    max_lateral_ratio: float = 0.3  # |mean lateral| / mean forward speed: forward walking only
    contact_height: float = 0.03  # m, sole height below which a foot may be in stance
    contact_speed: float = 0.25  # m/s, sole speed below which a foot may be in stance
    base_height: float = -0.03  # m, torso height offset from Digit's stand pose (as the TO walk)
    max_foot_error: float = 0.005  # m, IK sole error that rejects the clip
    ik: IKSettings = field(default_factory=IKSettings)


@dataclass
class Calibration:
    leg_ratio: float  # Digit hip height / human hip height
    arm_ratio: float
    human_leg: float
    robot_leg: float


def resample(positions: np.ndarray, fps: float) -> np.ndarray:
    """(T, ..., 3) at `fps` to 200 Hz by linear interpolation."""
    t_in = np.arange(len(positions)) / fps
    t_out = np.arange(int(np.floor(t_in[-1] / FRAME_DT)) + 1) * FRAME_DT
    flat = positions.reshape(len(positions), -1)
    out = np.stack([np.interp(t_out, t_in, flat[:, i]) for i in range(flat.shape[1])], axis=1)
    return out.reshape(len(t_out), *positions.shape[1:])


def _robot_geometry(robot: Robot) -> dict[str, np.ndarray]:
    """Stand-pose positions of the hips, shoulders, soles, hands and base site (MuJoCo)."""
    m, d = robot.mj_model, mujoco.MjData(robot.mj_model)
    d.qpos[:] = robot.stand_qpos
    mujoco.mj_kinematics(m, d)
    ee = robot.config.end_effectors

    def body(name: str) -> np.ndarray:
        return d.xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)].copy()

    def joint_body(joint: str) -> np.ndarray:
        return d.xanchor[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, joint)].copy()

    out = {name: d.site_xpos[robot.site_id(site)].copy() for name, site in ee.items()}
    out["base"] = d.site_xpos[robot.site_id(robot.config.imu_site)].copy()
    out["base_body"] = body(robot.config.base_body)
    for side in ("left", "right"):
        out[f"{side}_hip"] = joint_body(f"{side}_hip_pitch")
        out[f"{side}_shoulder"] = joint_body(f"{side}_shoulder_pitch")
    return out


def robot_leg_length(robot: Robot, g: dict[str, np.ndarray] | None = None) -> float:
    """m from the soles to the hip pitch joints in the stand pose: the leg the human's is scaled to."""
    g = g or _robot_geometry(robot)
    return float(0.5 * (g["left_hip"][2] + g["right_hip"][2]) - 0.5 * (g["left_foot"][2] + g["right_foot"][2]))


def calibrate(robot: Robot, kp: dict[str, np.ndarray]) -> Calibration:
    g = _robot_geometry(robot)
    robot_leg = robot_leg_length(robot, g)
    hips = 0.5 * (kp["left_hip"][:, 2] + kp["right_hip"][:, 2])
    human_leg = float(np.percentile(hips, 90))
    if not human_leg > 0.2:
        raise DataError(f"the human hip height is {human_leg:.3f} m after grounding: not a standing or walking body")
    arm_ratio = 1.0
    if all(k in kp for k in ("left_shoulder", "left_wrist")):
        human_arm = float(np.median(np.linalg.norm(kp["left_wrist"] - kp["left_shoulder"], axis=1)))
        robot_arm = float(np.linalg.norm(g["left_hand"] - g["left_shoulder"]))
        arm_ratio = robot_arm / max(human_arm, 1e-3)
    return Calibration(float(robot_leg / human_leg), arm_ratio, human_leg, float(robot_leg))


def ground_and_align(kp: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Floor at z = 0 (standing ankle height taken from the lowest ankles), walking along +x from xy = 0."""
    ankles = np.concatenate([kp["left_ankle"][:, 2], kp["right_ankle"][:, 2]])
    toes = [kp[k][:, 2] for k in ("left_toe", "right_toe") if k in kp]
    floor = min(float(np.percentile(np.concatenate(toes), 1)), float(np.percentile(ankles, 1)) - 0.06) if toes \
        else float(np.percentile(ankles, 1)) - 0.08
    travel = kp["pelvis"][-1, :2] - kp["pelvis"][0, :2]
    yaw = float(np.arctan2(travel[1], travel[0])) if np.linalg.norm(travel) > 0.05 else 0.0
    R = yaw_matrix(-yaw)
    origin = np.array([*kp["pelvis"][0, :2], floor])
    return {k: (v - origin) @ R.T for k, v in kp.items()}


def _heading(kp: dict[str, np.ndarray]) -> np.ndarray:
    """Torso heading (T,) from the hip line (left minus right hip is the body's left)."""
    left = kp["left_hip"][:, :2] - kp["right_hip"][:, :2]
    return np.unwrap(np.arctan2(left[:, 1], left[:, 0]) - 0.5 * np.pi)


def _smooth(x: np.ndarray, frames: int = 9) -> np.ndarray:
    kernel = np.ones(frames) / frames
    pad = np.pad(x, [(frames // 2, frames // 2)] + [(0, 0)] * (x.ndim - 1), mode="edge")
    return np.apply_along_axis(lambda c: np.convolve(c, kernel, mode="valid"), 0, pad)


def foot_tracks(kp: dict[str, np.ndarray], calib: Calibration, robot_geom: dict[str, np.ndarray],
                settings: RetargetSettings) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], np.ndarray]:
    """Sole positions (T, 3) and yaws (T,) of each foot, and the stance schedule (T, 2)."""
    s = calib.leg_ratio
    pelvis = kp["pelvis"] * s
    soles, yaws, stance = {}, {}, []
    stand_half = {f: robot_geom[f][1] - 0.5 * (robot_geom["left_foot"][1] + robot_geom["right_foot"][1]) for f in FEET}
    for foot in FEET:
        side = SIDES[foot]
        ankle = kp[f"{side}_ankle"] * s
        toe = kp.get(f"{side}_toe")
        sole = ankle.copy() if toe is None else 0.5 * (ankle + toe * s)
        ground = float(np.percentile(sole[:, 2], 2))
        sole[:, 2] = np.maximum(sole[:, 2] - ground, 0.0)
        lateral = float(np.mean(sole[:, 1] - pelvis[:, 1]))
        sole[:, 1] += stand_half[foot] - lateral  # Digit's stance width
        if toe is None:
            yaw = _heading(kp)
        else:
            d = toe[:, :2] - kp[f"{side}_ankle"][:, :2]
            yaw = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        sole = _smooth(sole)
        speed = np.linalg.norm(np.gradient(sole[:, :2], FRAME_DT, axis=0), axis=1)
        on = (sole[:, 2] < settings.contact_height) & (speed < settings.contact_speed)
        on = _smooth(on.astype(float), 11) > 0.5
        sole, yaw = _hold_stance(sole, _smooth(yaw), on)
        soles[foot], yaws[foot] = sole, yaw
        stance.append(on)
    return soles, yaws, np.stack(stance, axis=1)


def _hold_stance(sole: np.ndarray, yaw: np.ndarray, on: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A stance sole stays where its stance began, on the floor; the swing before and after is
    blended into it over 0.1 s so that the foot lands and lifts without a jump."""
    sole, yaw = sole.copy(), yaw.copy()
    edges = np.flatnonzero(np.diff(np.concatenate([[0], on.astype(int), [0]])))
    blend = int(0.1 / FRAME_DT)
    for a, b in zip(edges[::2], edges[1::2]):
        hold, hold_yaw = np.array([*sole[a, :2], 0.0]), yaw[a]
        for lo, hi, towards in ((max(a - blend, 0), a, True), (b, min(b + blend, len(sole)), False)):
            for k in range(lo, hi):
                w = (k - lo + 1) / (hi - lo + 1) if towards else 1.0 - (k - lo + 1) / (hi - lo + 1)
                sole[k] = (1 - w) * sole[k] + w * hold
                yaw[k] = (1 - w) * yaw[k] + w * hold_yaw
        sole[a:b], yaw[a:b] = hold, hold_yaw
    sole[:, 2] = np.maximum(sole[:, 2], 0.0)
    return sole, yaw


def keypoint_targets(robot: Robot, motion: HumanMotion, settings: RetargetSettings
                     ) -> tuple[list[FrameTargets], np.ndarray, Calibration, dict[str, float]]:
    """The IK targets of every 200 Hz frame, the stance schedule, the calibration and the clip's figures."""
    kp = ground_and_align({k: resample(v, motion.fps) for k, v in motion.keypoints().items()})
    calib = calibrate(robot, kp)
    geom = _robot_geometry(robot)
    s = calib.leg_ratio
    soles, yaws, stance = foot_tracks(kp, calib, geom, settings)
    heading = _smooth(_heading(kp), 41)
    pelvis = _smooth(kp["pelvis"] * s)
    base_z = geom["base"][2] + settings.base_height + (pelvis[:, 2] - np.median(pelvis[:, 2]))
    base_xy = pelvis[:, :2]
    hands = {}
    for side in ("left", "right"):
        if f"{side}_wrist" in kp and f"{side}_shoulder" in kp:
            rel = kp[f"{side}_wrist"] - kp[f"{side}_shoulder"]
            c, sn = np.cos(heading), np.sin(heading)  # into the heading frame
            rel = np.stack([c * rel[:, 0] + sn * rel[:, 1], -sn * rel[:, 0] + c * rel[:, 1], rel[:, 2]], 1)
            shoulder_in_base = geom[f"{side}_shoulder"] - geom["base"]
            hands[f"{side}_hand"] = shoulder_in_base + calib.arm_ratio * _smooth(rel)
    targets = []
    for k in range(len(pelvis)):
        targets.append(FrameTargets(
            feet={f: (soles[f][k], yaw_matrix(float(yaws[f][k]))) for f in FEET},
            base_rotation=yaw_matrix(float(heading[k])),
            base_position=np.array([*base_xy[k], base_z[k]]),
            base_axes=(1.0, 1.0, 1.0),
            hands_in_base={h: v[k] for h, v in hands.items()} or None,
        ))
    figures = clip_figures(pelvis, soles, stance)
    return targets, stance, calib, figures


def clip_figures(pelvis: np.ndarray, soles: dict[str, np.ndarray], stance: np.ndarray) -> dict[str, float]:
    duration = (len(pelvis) - 1) * FRAME_DT
    velocity = (pelvis[-1, :2] - pelvis[0, :2]) / max(duration, FRAME_DT)
    apexes = []
    for j, foot in enumerate(FEET):
        swing = ~stance[:, j]
        edges = np.flatnonzero(np.diff(np.concatenate([[0], swing.astype(int), [0]])))
        apexes += [float(soles[foot][a:b, 2].max()) for a, b in zip(edges[::2], edges[1::2]) if b - a > 10]
    return {
        "speed": float(velocity[0]),
        "lateral_speed": float(velocity[1]),
        "clearance": float(np.median(apexes)) if apexes else 0.0,
        "steps": float(len(apexes)),
        "duration": float(duration),
    }


def filter_errors(figures: dict[str, float], foot_error: float, settings: RetargetSettings) -> dict[str, dict[str, Any]]:
    """The filters as task figures: each value is how far the clip is outside its range (0: inside)."""
    lo, hi = settings.speed_range
    c_lo, c_hi = settings.clearance_range
    speed, lateral = figures["speed"], figures["lateral_speed"]
    return {
        "speed_out_of_range": {"value": max(lo - speed, speed - hi, 0.0), "limit": 0.0, "unit": "m/s"},
        "clearance_out_of_range": {"value": max(c_lo - figures["clearance"], figures["clearance"] - c_hi, 0.0),
                                   "limit": 0.0, "unit": "m"},
        "not_forward_walking": {"value": max(abs(lateral) - settings.max_lateral_ratio * max(speed, 0.0), 0.0)
                                + (1.0 if figures["steps"] < 2 else 0.0), "limit": 0.0, "unit": "m/s"},
        "ik_foot_error": {"value": float(foot_error), "limit": settings.max_foot_error, "unit": "m"},
    }


def retarget(robot: Robot, motion: HumanMotion, settings: RetargetSettings = RetargetSettings(), *,
             seed: int = 0) -> tuple[Trajectory, dict[str, dict[str, Any]]]:
    """The Digit record of `motion` and its filter figures (for `validate`'s task errors)."""
    start = time.perf_counter()
    targets, stance, calib, figures = keypoint_targets(robot, motion, settings)
    result = KeypointIK(robot, settings.ik).solve(targets)
    params = {"speed": figures["speed"], "clearance": figures["clearance"], "leg_ratio": calib.leg_ratio}
    stats = {
        "name": f"retarget + QP differential IK (mink, {settings.ik.solver})",
        "iterations": int(result.iterations.sum()),
        "foot_error_max": float(result.foot_error.max()),
        "calibration": vars(calib),
        "clip": {**figures, "file": motion.source, "fps": motion.fps},
        "solve_time": time.perf_counter() - start,
    }
    traj = kinematic_trajectory(robot, result.qpos, stance, task=TASK, source="human", contact_names=FEET,
                                params=params, seed=seed, solver=stats,
                                provenance=provenance(robot.hash, source_file=motion.source))
    traj.solver["total_time"] = time.perf_counter() - start
    return traj, filter_errors(figures, float(result.foot_error.max()), settings)
