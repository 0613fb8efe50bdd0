"""A reader for AMASS-style SMPL(-H) `.npz` motions: `poses`, `trans`, `mocap_framerate` (`betas` unused).

Without the SMPL body model (licensed, not shipped here) the joint positions come from forward
kinematics on the standard SMPL kinematic tree (22 body joints, parents `PARENTS`) with rest-pose
offsets built from textbook adult proportions: segment lengths as fractions of body height H
(D. A. Winter, *Biomechanics and Motor Control of Human Movement*, 4th ed., Fig. 4.1: thigh
0.245 H, shank 0.246 H, ankle height 0.039 H, foot 0.152 H, hip width 0.191 H, shoulder width
0.259 H, upper arm 0.186 H, forearm 0.146 H, shoulder height 0.818 H, hip height 0.530 H) with
H = 1.70 m. These are not SMPL's exact joints and `betas` (the body shape) are ignored; the
retargeting rescales every segment to Digit anyway, and the leg length it uses for the speed
scaling comes from the joint positions themselves. A file that holds joint positions already
(`joints`, `Jtr` or `joint_positions`, (T, J, 3), metres, in SMPL joint order) is read as is,
which is exact: export them with the SMPL-H model next to your AMASS download to get SMPL's own.

The rest pose is SMPL's: y up, facing +z, the body's left at +x. `poses[:, :3]` is the root
orientation (axis-angle) that takes it into the dataset's world, z up in AMASS.
"""

from __future__ import annotations

from pathlib import Path
from zipfile import BadZipFile

import numpy as np
from scipy.spatial.transform import Rotation

from opt2skill.errors import DataError
from opt2skill.retarget.motion import HumanMotion, up_to_z

JOINTS = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle", "right_ankle",
    "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)
PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)

H = 1.70  # m, body height of the offsets below


def _offsets() -> np.ndarray:
    """Rest-pose offsets (22, 3) from each joint's parent, SMPL's frame (x left, y up, z forward)."""
    hip_half, shoulder_half = 0.5 * 0.191 * H * 0.5, 0.5 * 0.259 * H  # hip joint centres ~half the hip width
    thigh, shank, ankle, foot = 0.245 * H, 0.246 * H, 0.039 * H, 0.152 * H
    hip_h, shoulder_h = 0.530 * H, 0.818 * H
    trunk = shoulder_h - hip_h - 0.03 * H  # pelvis (a little above the hips) to shoulders: 4 spine/neck segments
    upper, fore = 0.186 * H, 0.146 * H
    o = np.zeros((22, 3))
    # o[0] = 0: the pelvis is at `trans` (SMPL's rest pelvis is near the model origin; its offset is ignored)
    o[1], o[2] = (hip_half, -0.03 * H, 0), (-hip_half, -0.03 * H, 0)
    o[3], o[6], o[9] = (0, 0.25 * trunk, 0), (0, 0.25 * trunk, 0), (0, 0.25 * trunk, 0)
    o[4], o[5] = (0, -thigh, 0), (0, -thigh, 0)
    o[7], o[8] = (0, -shank, 0), (0, -shank, 0)
    o[10], o[11] = (0, -ankle, 0.75 * foot), (0, -ankle, 0.75 * foot)  # toes: forward and down to the floor
    o[12] = (0, 0.25 * trunk, 0)
    o[13], o[14] = (0.35 * shoulder_half, 0.2 * trunk, 0), (-0.35 * shoulder_half, 0.2 * trunk, 0)
    o[15] = (0, 0.07 * H, 0)
    o[16], o[17] = (0.65 * shoulder_half, 0.05 * trunk, 0), (-0.65 * shoulder_half, 0.05 * trunk, 0)
    o[18], o[19] = (upper, 0, 0), (-upper, 0, 0)  # SMPL's rest pose is a T-pose: arms along x
    o[20], o[21] = (fore, 0, 0), (-fore, 0, 0)
    return o


OFFSETS = _offsets()


def smpl_forward_kinematics(poses: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """(T, 22, 3) joint positions from axis-angle `poses` (T, >= 66) and root translation `trans` (T, 3).

    The pelvis is at `trans`; each joint hangs from its parent by its rest offset turned by the
    parent's global rotation (the product of the axis-angle rotations down the tree).
    """
    n = len(poses)
    rot = Rotation.from_rotvec(poses[:, :66].reshape(n * 22, 3)).as_matrix().reshape(n, 22, 3, 3)
    pos = np.zeros((n, 22, 3))
    glob = np.zeros((n, 22, 3, 3))
    for j, parent in enumerate(PARENTS):
        if parent < 0:
            glob[:, j] = rot[:, j]
            pos[:, j] = trans
        else:
            glob[:, j] = glob[:, parent] @ rot[:, j]
            pos[:, j] = pos[:, parent] + np.einsum("tij,j->ti", glob[:, parent], OFFSETS[j])
    return pos


def read_smpl(path: str | Path, up: str = "z") -> HumanMotion:
    """Joint positions of an AMASS-style `.npz` file, metres, z up (`up`: the file's world up axis)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"SMPL motion file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except (OSError, ValueError, BadZipFile) as exc:
        raise DataError(f"{path}: not a readable .npz file ({exc})") from None
    rate = next((data[k] for k in ("mocap_framerate", "mocap_frame_rate", "fps") if k in data), None)
    if rate is None:
        raise DataError(f"{path}: no frame rate (mocap_framerate) in the file; it has {sorted(data)}")
    fps = float(np.asarray(rate).reshape(-1)[0])
    if not fps > 0:
        raise DataError(f"{path}: frame rate {fps:g} must be > 0")
    given = next((k for k in ("joints", "Jtr", "joint_positions") if k in data), None)
    if given is not None:
        positions = np.asarray(data[given], dtype=float)
        if positions.ndim != 3 or positions.shape[2] != 3 or positions.shape[1] < 22:
            raise DataError(f"{path}: '{given}' should be (frames, >= 22 joints, 3), got {positions.shape}")
        positions = positions[:, :22]
    else:
        missing = [k for k in ("poses", "trans") if k not in data]
        if missing:
            raise DataError(f"{path}: not an AMASS-style motion: missing {missing}; it has {sorted(data)}")
        poses, trans = np.asarray(data["poses"], dtype=float), np.asarray(data["trans"], dtype=float)
        if poses.ndim != 2 or poses.shape[1] < 66 or trans.shape != (len(poses), 3):
            raise DataError(f"{path}: poses (T, >= 66) and trans (T, 3) expected, got {poses.shape} and {trans.shape}")
        positions = smpl_forward_kinematics(poses, trans)
    if len(positions) < 2 or not np.all(np.isfinite(positions)):
        raise DataError(f"{path}: the motion needs at least 2 frames of finite numbers")
    return HumanMotion(JOINTS, up_to_z(positions, up), fps, str(path))
