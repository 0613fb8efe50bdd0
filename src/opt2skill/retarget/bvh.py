"""A reader for BVH (Biovision hierarchy) motion files: joint positions by forward kinematics.

The format: `HIERARCHY`, then nested `ROOT`/`JOINT` blocks with an `OFFSET x y z`, a
`CHANNELS n ...` line (positions and rotations in the order given) and `End Site` blocks; then
`MOTION`, `Frames: N`, `Frame Time: dt` and one line of N channel values per frame. A joint's local
transform is a translation (its offset plus its position channels) followed by its rotation
channels applied in the listed order (R = R_1 R_2 R_3, angles in degrees). End sites are joints
named `<parent>_end`. Units: BVH files are usually centimetres; `unit` scales to metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from opt2skill.errors import DataError
from opt2skill.retarget.motion import HumanMotion, up_to_z

_AXES = {"xrotation": "x", "yrotation": "y", "zrotation": "z"}
_POS = {"xposition": 0, "yposition": 1, "zposition": 2}


@dataclass
class _Joint:
    name: str
    parent: int
    offset: np.ndarray
    channels: list[str] = field(default_factory=list)
    first_channel: int = 0


class _Tokens:
    def __init__(self, text: str, path: Path):
        self.words, self.i, self.path = text.split(), 0, path

    def next(self, what: str) -> str:
        if self.i >= len(self.words):
            raise DataError(f"{self.path}: not a BVH file: the file ends where {what} was expected")
        self.i += 1
        return self.words[self.i - 1]

    def expect(self, word: str) -> None:
        got = self.next(f"'{word}'")
        if got.upper() != word.upper():
            raise DataError(f"{self.path}: not a BVH file: expected '{word}', found '{got[:40]}'")

    def number(self, what: str) -> float:
        word = self.next(what)
        try:
            return float(word)
        except ValueError:
            raise DataError(f"{self.path}: not a BVH file: {what} should be a number, found '{word[:40]}'") from None


def _parse_joint(tok: _Tokens, name: str, parent: int, joints: list[_Joint], channels: list[int]) -> None:
    tok.expect("{")
    tok.expect("OFFSET")
    joint = _Joint(name, parent, np.array([tok.number("an offset") for _ in range(3)]))
    index = len(joints)
    joints.append(joint)
    while True:
        word = tok.next("a joint entry or '}'")
        key = word.upper()
        if key == "CHANNELS":
            n = int(tok.number("the channel count"))
            joint.channels = [tok.next("a channel name").lower() for _ in range(n)]
            unknown = [c for c in joint.channels if c not in _AXES and c not in _POS]
            if unknown:
                raise DataError(f"{tok.path}: joint '{name}' has unknown channels {unknown}")
            joint.first_channel = channels[0]
            channels[0] += n
        elif key == "JOINT":
            _parse_joint(tok, tok.next("a joint name"), index, joints, channels)
        elif key == "END":
            tok.expect("Site")
            tok.expect("{")
            tok.expect("OFFSET")
            joints.append(_Joint(f"{name}_end", index, np.array([tok.number("an offset") for _ in range(3)])))
            tok.expect("}")
        elif key == "}":
            return
        else:
            raise DataError(f"{tok.path}: not a BVH file: unexpected '{word[:40]}' in joint '{name}'")


def read_bvh(path: str | Path, unit: float | None = None, up: str = "y") -> HumanMotion:
    """Joint positions of every frame of a BVH file, in metres with z up.

    `unit`: metres per file unit (None: 0.01 if the skeleton is taller than 10 units, else 1).
    `up`: the file's up axis ('y' for most BVH files).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"BVH file not found: {path}")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: not a readable BVH text file ({exc})") from None
    tok = _Tokens(text, path)
    tok.expect("HIERARCHY")
    tok.expect("ROOT")
    joints: list[_Joint] = []
    count = [0]
    _parse_joint(tok, tok.next("the root's name"), -1, joints, count)
    tok.expect("MOTION")
    tok.expect("Frames:")
    frames = int(tok.number("the frame count"))
    tok.expect("Frame")
    tok.expect("Time:")
    dt = tok.number("the frame time")
    if frames < 2 or not dt > 0:
        raise DataError(f"{path}: a BVH motion needs at least 2 frames and a frame time > 0 (got {frames}, {dt:g})")
    values = tok.words[tok.i:]
    if len(values) < frames * count[0]:
        raise DataError(f"{path}: the motion has {len(values)} values; {frames} frames of {count[0]} channels need "
                        f"{frames * count[0]} (the file is truncated)")
    try:
        data = np.array(values[: frames * count[0]], dtype=float).reshape(frames, count[0])
    except ValueError:
        raise DataError(f"{path}: the motion data holds something that is not a number") from None
    positions = forward_kinematics(joints, data)
    if unit is None:
        height = float(np.ptp(positions[0], axis=0).max())
        unit = 0.01 if height > 10.0 else 1.0
    return HumanMotion(tuple(j.name for j in joints), up_to_z(positions * unit, up), 1.0 / dt, str(path))


def forward_kinematics(joints: list[_Joint], data: np.ndarray) -> np.ndarray:
    """(T, J, 3) world positions of the joints from the channel values (T, channels)."""
    n = len(data)
    pos = np.zeros((n, len(joints), 3))
    rot = np.zeros((n, len(joints), 3, 3))
    for j, joint in enumerate(joints):
        local_t = np.tile(joint.offset, (n, 1))
        local_r = np.tile(np.eye(3), (n, 1, 1))
        axes = "".join(_AXES[c] for c in joint.channels if c in _AXES)
        if axes:
            cols = [joint.first_channel + k for k, c in enumerate(joint.channels) if c in _AXES]
            local_r = Rotation.from_euler(axes.upper(), data[:, cols], degrees=True).as_matrix()  # intrinsic
        for k, c in enumerate(joint.channels):
            if c in _POS:
                local_t[:, _POS[c]] += data[:, joint.first_channel + k]
        if joint.parent < 0:
            pos[:, j], rot[:, j] = local_t, local_r
        else:
            p = joint.parent
            pos[:, j] = pos[:, p] + np.einsum("tij,tj->ti", rot[:, p], local_t)
            rot[:, j] = rot[:, p] @ local_r
    return pos
