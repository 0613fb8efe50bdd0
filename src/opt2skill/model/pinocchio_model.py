"""The robot in Pinocchio, parsed from the same MJCF as MuJoCo, with the config's limits set.

Pinocchio's MJCF parser reads joint ranges and armature but leaves effort and velocity limits at
infinity and ignores <option gravity>; this module sets them (docs/model.md).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from opt2skill.errors import ModelError
from opt2skill.robots import RobotConfig


def build_pinocchio(config: RobotConfig, gravity: np.ndarray) -> pin.Model:
    try:
        model = pin.buildModelFromMJCF(str(config.mjcf_path))
    except Exception as exc:
        raise ModelError(f"Pinocchio cannot read MJCF {config.mjcf_path}: {str(exc).strip()[:300]}") from None
    names = list(model.names)[1:]
    if not names or names[0] != config.root_joint or model.joints[1].shortname() != "JointModelFreeFlyer":
        raise ModelError(
            f"{config.mjcf_path}: Pinocchio did not find the free joint '{config.root_joint}' at the root"
        )
    if names[1:] != config.joint_names:
        raise ModelError(
            f"{config.mjcf_path}: Pinocchio's joint order {names[1:]} differs from robot "
            f"'{config.name}' config order {config.joint_names}"
        )
    bad = [n for n, j in zip(names[1:], list(model.joints)[2:]) if j.nq != 1 or j.nv != 1]
    if bad:
        raise ModelError(f"{config.mjcf_path}: joints {bad} are not single-axis in Pinocchio (one joint per body)")

    model.gravity.linear = np.asarray(gravity, dtype=float)
    # Free flyer: translation unbounded, quaternion components within the unit ball.
    model.lowerPositionLimit[:3] = -np.inf
    model.upperPositionLimit[:3] = np.inf
    model.lowerPositionLimit[3:7] = -1.0
    model.upperPositionLimit[3:7] = 1.0
    model.effortLimit[6:] = config.torque_limit
    model.velocityLimit[6:] = config.velocity_limit
    model.effortLimit[:6] = 0.0
    model.velocityLimit[:6] = np.inf
    return model
