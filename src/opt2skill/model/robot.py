"""One robot, two libraries: the same MJCF in MuJoCo (simulation) and Pinocchio (optimization)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin

from opt2skill.model import mujoco_model
from opt2skill.model.pinocchio_model import build_pinocchio
from opt2skill.robots import DEFAULT_ROBOT, RobotConfig, find_robot_config


@dataclass
class Robot:
    """A robot loaded into MuJoCo and Pinocchio with the same joint order, limits and gravity.

    `mj_model` is the robot on a flat floor with PD actuators and sensors. For other scenes, call
    `mj_spec()` for a fresh editable spec, add terrain or objects, and compile it.
    """

    config: RobotConfig
    mj_model: mujoco.MjModel
    pin_model: pin.Model
    stand_qpos: np.ndarray
    _pin_frames: dict[str, int] = field(default_factory=dict, repr=False)

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def nq(self) -> int:
        return self.mj_model.nq

    @property
    def nv(self) -> int:
        return self.mj_model.nv

    @property
    def nu(self) -> int:
        return self.mj_model.nu

    def mj_spec(self, floor: bool = True) -> mujoco.MjSpec:
        return mujoco_model.build_spec(self.config, floor=floor)

    def compile(self, spec: mujoco.MjSpec) -> mujoco.MjModel:
        return mujoco_model.compile_spec(spec, f"robot '{self.name}' scene")

    def pin_frame_id(self, site: str) -> int:
        """Pinocchio frame id of an MJCF site (Pinocchio keeps sites as operational frames)."""
        if site not in self._pin_frames:
            for fid, frame in enumerate(self.pin_model.frames):
                if frame.name == site and frame.type == pin.FrameType.OP_FRAME:
                    self._pin_frames[site] = fid
                    break
            else:
                raise KeyError(f"robot '{self.name}' has no site '{site}'")
        return self._pin_frames[site]

    def site_id(self, site: str) -> int:
        sid = mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_SITE, site)
        if sid < 0:
            raise KeyError(f"robot '{self.name}' has no site '{site}'")
        return sid

    @property
    def stand_q_pin(self) -> np.ndarray:
        from opt2skill.model.convert import qpos_mj_to_pin

        return qpos_mj_to_pin(self.stand_qpos)

    @property
    def hash(self) -> str:
        """sha256 of robot.yaml and the MJCF: recorded in every output for provenance."""
        return self.config.source_hash


def load_robot(name_or_path: str | Path = DEFAULT_ROBOT) -> Robot:
    """Load a built-in robot by name or a user's robot.yaml by path, checked end to end."""
    config = find_robot_config(name_or_path)
    spec = mujoco_model.build_spec(config)
    mj_model = mujoco_model.compile_spec(spec, str(config.mjcf_path))
    pin_model = build_pinocchio(config, gravity=mj_model.opt.gravity)
    return Robot(
        config=config,
        mj_model=mj_model,
        pin_model=pin_model,
        stand_qpos=mujoco_model.stand_qpos(mj_model, config),
    )
