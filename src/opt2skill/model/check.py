"""Does MuJoCo agree with Pinocchio on this robot? Worst-case differences at random states.

Used by the tests and by `opt2skill robot check`, which is the first thing to run after adding a
robot (docs/robots.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import pinocchio as pin

from opt2skill.geometry import quat_to_mat
from opt2skill.model.convert import gen_force_mj_to_pin, qpos_mj_to_pin, qvel_mj_to_pin, velocity_map
from opt2skill.model.robot import Robot


@dataclass(frozen=True)
class Agreement:
    """Largest absolute difference over all samples, per quantity (SI units)."""

    samples: int
    site_position: float
    site_rotation: float
    mass_matrix: float
    gravity: float
    bias: float  # gravity + Coriolis/centrifugal
    jacobian: float
    largest_coriolis: float  # size of the velocity terms compared, to show they were exercised

    def worst(self) -> float:
        return max(self.site_position, self.site_rotation, self.mass_matrix, self.gravity, self.bias, self.jacobian)


def random_states(robot: Robot, n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Random base poses, joint positions inside their ranges, and velocities (std 1.5)."""
    rng = np.random.default_rng(seed)
    m = robot.mj_model
    states = []
    for _ in range(n):
        qpos = robot.stand_qpos.copy()
        qpos[:3] = rng.uniform(-1, 1, 3) + [0, 0, 1]
        quat = rng.normal(size=4)
        qpos[3:7] = quat / np.linalg.norm(quat)
        qpos[7:] = rng.uniform(m.jnt_range[1:, 0], m.jnt_range[1:, 1])
        states.append((qpos, rng.normal(scale=1.5, size=m.nv)))
    return states


def compare(robot: Robot, n: int = 50, seed: int = 0) -> Agreement:
    m, pm = robot.mj_model, robot.pin_model
    d, d0, pd = mujoco.MjData(m), mujoco.MjData(m), pm.createData()
    sites = [m.site(i).name for i in range(m.nsite)]
    jac_sites = [f.sole_site for f in robot.config.feet] + [robot.config.end_effectors[h] for h in robot.config.hands]
    err = dict.fromkeys(["site_position", "site_rotation", "mass_matrix", "gravity", "bias", "jacobian"], 0.0)
    largest_coriolis = 0.0
    M_mj = np.zeros((m.nv, m.nv))
    jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))

    for qpos, qvel in random_states(robot, n, seed):
        d.qpos[:], d.qvel[:] = qpos, qvel
        mujoco.mj_forward(m, d)
        d0.qpos[:], d0.qvel[:] = qpos, 0.0
        mujoco.mj_forward(m, d0)
        q, v = qpos_mj_to_pin(qpos), qvel_mj_to_pin(qpos, qvel)
        T = velocity_map(qpos, m.nv)

        pin.framesForwardKinematics(pm, pd, q)
        for name in sites:
            oMf, sid = pd.oMf[robot.pin_frame_id(name)], robot.site_id(name)
            err["site_position"] = max(err["site_position"], np.abs(oMf.translation - d.site_xpos[sid]).max())
            err["site_rotation"] = max(err["site_rotation"], np.abs(oMf.rotation - d.site_xmat[sid].reshape(3, 3)).max())

        mujoco.mj_fullM(m, d, M_mj)
        M_pin = pin.crba(pm, pd, q)
        M_pin = np.triu(M_pin) + np.triu(M_pin, 1).T
        err["mass_matrix"] = max(err["mass_matrix"], np.abs(T.T @ M_mj @ T - M_pin).max())

        g_pin = pin.computeGeneralizedGravity(pm, pd, q)
        err["gravity"] = max(err["gravity"], np.abs(gen_force_mj_to_pin(qpos, d0.qfrc_bias) - g_pin).max())
        # With v_mj = T v_pin: c_pin = T^T (c_mj + M_mj dT/dt v_pin), where dT/dt v_pin = [R (w x v_lin); 0].
        tdot_v = np.zeros(m.nv)
        tdot_v[:3] = quat_to_mat(qpos[3:7]) @ np.cross(v[3:6], v[:3])
        nle = pin.nonLinearEffects(pm, pd, q, v)
        err["bias"] = max(err["bias"], np.abs(gen_force_mj_to_pin(qpos, d.qfrc_bias + M_mj @ tdot_v) - nle).max())
        largest_coriolis = max(largest_coriolis, np.abs(nle - g_pin).max())

        pin.computeJointJacobians(pm, pd, q)
        pin.updateFramePlacements(pm, pd)
        for name in jac_sites:
            mujoco.mj_jacSite(m, d, jacp, jacr, robot.site_id(name))
            J_pin = pin.getFrameJacobian(pm, pd, robot.pin_frame_id(name), pin.LOCAL_WORLD_ALIGNED)
            err["jacobian"] = max(err["jacobian"], np.abs(np.vstack([jacp, jacr]) @ T - J_pin).max())

    return Agreement(samples=n, largest_coriolis=largest_coriolis, **err)
