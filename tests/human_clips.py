"""Small constructed human walking clips (no real clip ships in a PyPI or Debian package; docs/baselines.md)."""

import numpy as np

from opt2skill.retarget.smpl import JOINTS


def smoothstep(s):
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3 - 2 * s)


def walking_joints(speed=1.0, clearance=0.15, hip_height=0.9, fps=60.0, duration=4.0, period=1.0):
    """(T, 22, 3) SMPL-order joint positions (metres, z up) of a person walking along +x at `speed`.

    Each foot swings 40 % of the gait `period` with its ankle raised by `clearance` at mid-swing,
    and stands still otherwise; the pelvis moves at constant speed at `hip_height` + 0.05 m.
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
        swing = np.clip((cycle - 0.6) / 0.4, 0, 1)  # swing in the last 40 % of each cycle
        x = stride * (k - phase) + speed * period * 0.2 + stride * smoothstep(swing) - 0.5 * stride
        z = ankle_h + clearance * np.sin(np.pi * swing) ** 2 * (cycle >= 0.6)
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
