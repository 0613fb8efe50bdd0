"""Constructed human walking clips: SMPL-order joint positions of a person walking along +x.

No real motion-capture clip ships in a PyPI or Debian package (docs/baselines.md), so the tests and
the quick setting of `opt2skill experiment table3` use these. They are not human data: a person's
gait reduced to a constant-speed pelvis, feet that swing on a smooth arc and stand still otherwise,
and still arms. A user with AMASS or BVH files passes those instead (`--human DIR`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from opt2skill.retarget.smpl import JOINTS

HIP_HEIGHT = 0.9  # m, an adult's (the leg length the retargeting scales by)


def _smoothstep(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3 - 2 * s)


def walking_joints(speed: float = 1.0, clearance: float = 0.15, hip_height: float = HIP_HEIGHT, fps: float = 60.0,
                   duration: float = 4.0, period: float = 1.0, swing_share: float = 0.4) -> tuple[np.ndarray, float]:
    """(T, 22, 3) SMPL-order joint positions (metres, z up) of a person walking along +x at `speed`.

    Each foot swings `swing_share` of the gait `period` with its ankle raised by `clearance` at
    mid-swing, and stands still otherwise; the pelvis moves at constant speed at `hip_height` + 0.05 m.
    """
    t = np.arange(int(duration * fps) + 1) / fps
    n, J = len(t), {name: i for i, name in enumerate(JOINTS)}
    p = np.zeros((n, len(JOINTS), 3))
    pelvis = np.stack([speed * t, np.zeros(n), np.full(n, hip_height + 0.05)], 1)
    stride = speed * period
    ankle_h = 0.07
    for side, y, phase in (("left", 0.09, 0.0), ("right", -0.09, 0.5)):
        cycle = (t / period + phase) % 1.0
        k = np.floor(t / period + phase)
        lift = 1.0 - swing_share
        swing = np.clip((cycle - lift) / swing_share, 0, 1)  # swing at the end of each cycle
        x = stride * (k - phase) + speed * period * 0.2 + stride * _smoothstep(swing) - 0.5 * stride
        z = ankle_h + clearance * np.sin(np.pi * swing) ** 2 * (cycle >= lift)
        ankle = np.stack([x, np.full(n, y), z], 1)
        hip = pelvis + [0, y, -0.05]
        p[:, J[f"{side}_hip"]] = hip
        p[:, J[f"{side}_ankle"]] = ankle
        p[:, J[f"{side}_knee"]] = 0.5 * (hip + ankle) + [0.04, 0, 0]
        p[:, J[f"{side}_foot"]] = ankle + [0.13, 0, -ankle_h]
        shoulder = pelvis + [0, 2 * y + 0.02 * np.sign(y), 0.5]
        p[:, J[f"{side}_collar"]] = shoulder - [0, 0.08 * np.sign(y), 0]
        p[:, J[f"{side}_shoulder"]] = shoulder
        p[:, J[f"{side}_elbow"]] = shoulder + [0, 0, -0.28]
        p[:, J[f"{side}_wrist"]] = shoulder + [0.05, 0, -0.52]
    p[:, J["pelvis"]] = pelvis
    for i, name in enumerate(("spine1", "spine2", "spine3", "neck", "head")):
        p[:, J[name]] = pelvis + [0, 0, 0.12 * (i + 1)]
    return p, fps


def write_walking_clips(folder: Path, n: int, seed: int, speed: tuple[float, float], clearance: tuple[float, float],
                        duration: float, leg_ratio: float) -> list[Path]:
    """`n` clips as AMASS-style `.npz` files holding joint positions (`joints`, `mocap_framerate`),
    speed and ankle clearance drawn uniformly (seeded) so that, scaled by `leg_ratio` (the robot's
    leg over `HIP_HEIGHT`), they fall in the robot-scale ranges given. Existing files are kept:
    clip i depends only on (seed, i), so a rerun writes the same clips."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        path = folder / f"synthetic_{seed:03d}_{i:05d}.npz"
        paths.append(path)
        if path.is_file():
            continue
        rng = np.random.default_rng([seed, i])
        v, c = rng.uniform(*speed), rng.uniform(*clearance)
        # A one-second gait with half of it in swing: with the 40 % swing of `walking_joints`' default,
        # Digit's knees exceed their speed limit at most speeds and clearances (measured).
        joints, fps = walking_joints(speed=v / leg_ratio, clearance=c / leg_ratio, duration=duration,
                                     period=float(rng.uniform(0.95, 1.05)), swing_share=0.5)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, joints=joints, mocap_framerate=np.array(fps), speed=np.array(v), clearance=np.array(c))
        tmp.rename(path)  # whole or absent: a killed run leaves no half clip
    return paths
