"""A human motion as joint positions, and the keypoints the retargeting reads from it.

Readers (`bvh`, `smpl`) return a `HumanMotion`: world positions of named joints in metres, z up,
at the clip's own frame rate. `keypoints` finds the joints the pipeline needs by their usual names.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from opt2skill.errors import DataError

# keypoint -> joint names tried in order (case-insensitive): SMPL names, then common BVH names.
KEYPOINTS: dict[str, tuple[str, ...]] = {
    "pelvis": ("pelvis", "hips", "hip", "root"),
    "left_hip": ("left_hip", "leftupleg", "lhipjoint", "lefthip", "leftthigh", "lthigh"),
    "right_hip": ("right_hip", "rightupleg", "rhipjoint", "righthip", "rightthigh", "rthigh"),
    "left_knee": ("left_knee", "leftleg", "leftknee", "leftshin", "lshin"),
    "right_knee": ("right_knee", "rightleg", "rightknee", "rightshin", "rshin"),
    "left_ankle": ("left_ankle", "leftfoot", "leftankle", "lfoot"),
    "right_ankle": ("right_ankle", "rightfoot", "rightankle", "rfoot"),
    "left_toe": ("left_foot", "lefttoebase", "lefttoe", "ltoes", "lefttoes"),
    "right_toe": ("right_foot", "righttoebase", "righttoe", "rtoes", "righttoes"),
    "left_shoulder": ("left_shoulder", "leftarm", "leftshoulder", "lhumerus", "leftupperarm"),
    "right_shoulder": ("right_shoulder", "rightarm", "rightshoulder", "rhumerus", "rightupperarm"),
    "left_wrist": ("left_wrist", "lefthand", "leftwrist", "lwrist"),
    "right_wrist": ("right_wrist", "righthand", "rightwrist", "rwrist"),
}
REQUIRED = ("pelvis", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle")


@dataclass
class HumanMotion:
    joints: tuple[str, ...]
    positions: np.ndarray  # (T, J, 3) world, metres, z up
    fps: float
    source: str  # the file it was read from

    def keypoints(self) -> dict[str, np.ndarray]:
        """keypoint -> (T, 3) positions; a DataError names the required ones that are missing."""
        lower = {name.lower().replace(" ", "").replace(":", ""): i for i, name in enumerate(self.joints)}
        # Strip common prefixes such as "mixamorig" so that "mixamorigLeftUpLeg" matches.
        for name, i in list(lower.items()):
            for prefix in ("mixamorig", "bip01", "character"):
                if name.startswith(prefix):
                    lower.setdefault(name[len(prefix):], i)
        out = {}
        for key, names in KEYPOINTS.items():
            for name in names:
                if name in lower:
                    out[key] = self.positions[:, lower[name]]
                    break
        missing = [k for k in REQUIRED if k not in out]
        if missing:
            raise DataError(f"{self.source}: no joint for {missing}; joints: {', '.join(self.joints)}")
        return out


def up_to_z(positions: np.ndarray, up: str) -> np.ndarray:
    """Positions with axis `up` ('y' or 'z') turned to z by a proper rotation (y up: (x, y, z) -> (z, x, y))."""
    if up == "z":
        return positions
    if up == "y":
        return positions[..., [2, 0, 1]]
    raise DataError(f"up axis must be 'y' or 'z', got '{up}'")
