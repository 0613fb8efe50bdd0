"""Two hands squeezing what they hold, inside the optimizer's dynamics.

An object held between two hands by friction needs them to press on it: an equal and opposite pair
of forces of size s along the line between the hand points, each pushing its hand away from the
other. The pair exerts no net force or moment on the robot, so it does not change the robot's
motion, but the arms must hold it: the joints see the generalized force

    sigma(q) = s (J_1 - J_2)^T a = s grad_q |p_1 - p_2|,   a = (p_1 - p_2) / |p_1 - p_2|,

the gradient of s times the distance between the hands. `SqueezeActuation` is the floating-base
actuation with that force added, tau = [0; u] + sigma(q): the controls u are the motors' torques,
so the solver's torque bounds apply to what the motors give while they also hold the squeeze.

Only joints that move one hand and not the other change the distance (moving both, e.g. the
floating base, carries the two points rigidly), so sigma and its derivative live in those columns.
Its derivative is exact: for revolute joints i before j on a hand's chain, d J_j / d q_i = w_i x J_j
(w_i the axis of joint i in world axes, J_j the point's velocity per unit joint j speed), so

    d sigma / d q = s [ (J_1 - J_2)^T (I - a a^T) (J_1 - J_2) / |p_1 - p_2| + a . (d2 p_1 - d2 p_2) ].
"""

from __future__ import annotations

import crocoddyl
import numpy as np
import pinocchio as pin

from opt2skill.errors import ConfigError

class SqueezeActuation(crocoddyl.ActuationModelAbstract):
    """Floating-base actuation plus a squeeze of `squeeze` N between Pinocchio frames `frames`."""

    def __init__(self, state: crocoddyl.StateMultibody, frames: tuple[int, int], squeeze: float):
        crocoddyl.ActuationModelAbstract.__init__(self, state, state.nv - 6)
        self.model = state.pinocchio
        self.data = self.model.createData()
        self.frames = frames
        self.squeeze = float(squeeze)
        self.nq, self.nv = self.model.nq, self.model.nv
        self.columns, self.before = _one_sided_columns(self.model, frames)

    def generalized_force(self, q: np.ndarray) -> np.ndarray:
        """sigma(q) (nv,): the squeeze pair's generalized force on the robot."""
        out = np.zeros(self.nv)
        out[self.columns] = self._gradient(q)
        return out

    def _kinematics(self, q: np.ndarray):
        """(J_1, J_2) (6, c) in world axes over `columns`, and the unit axis and distance p_1 - p_2."""
        m, d = self.model, self.data
        pin.computeJointJacobians(m, d, q)
        pin.updateFramePlacements(m, d)
        jac = [pin.getFrameJacobian(m, d, fid, pin.LOCAL_WORLD_ALIGNED)[:, self.columns] for fid in self.frames]
        gap = d.oMf[self.frames[0]].translation - d.oMf[self.frames[1]].translation
        distance = float(np.sqrt(gap @ gap))
        return jac, gap / distance, distance

    def _gradient(self, q: np.ndarray) -> np.ndarray:
        (j1, j2), axis, _ = self._kinematics(q)
        return self.squeeze * (j1[:3] - j2[:3]).T @ axis

    def calc(self, data, x, u) -> None:
        data.tau[:] = 0.0
        data.tau[6:] = u
        data.tau[self.columns] += self._gradient(x[: self.nq])

    def calcDiff(self, data, x, u) -> None:
        (j1, j2), axis, distance = self._kinematics(x[: self.nq])
        jd = j1[:3] - j2[:3]
        hessian = jd.T @ (jd - np.outer(axis, axis @ jd)) / distance
        # a . d2p/dq_i dq_j = a . (w_i x v_j) = (a x w_i) . v_j for i before j on the chain (and i == j)
        ax, ay, az = axis
        skew = np.array([[0.0, -az, ay], [az, 0.0, -ax], [-ay, ax, 0.0]])  # skew @ w = a x w
        second = (skew @ j1[3:]).T @ j1[:3] - (skew @ j2[3:]).T @ j2[:3]
        hessian += np.where(self.before, second, second.T)
        data.dtau_dx[np.ix_(self.columns, self.columns)] = self.squeeze * hessian

    def commands(self, data, x, tau) -> None:
        data.u[:] = tau[6:] - self.generalized_force(x[: self.nq])[6:]

    def torqueTransform(self, data, x, u) -> None:
        data.Mtau[:, 6:] = np.eye(self.nu)

    def createData(self):
        data = crocoddyl.ActuationDataAbstract(self)
        data.dtau_du[6:, :] = np.eye(self.nu)
        data.tau_set[:] = [False] * 6 + [True] * self.nu
        return data


def _one_sided_columns(model: pin.Model, frames: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Velocity indices of the joints that support one of the frames but not both (one-DoF joints),
    and (c, c) bool: column i's joint is column j's or one before it on its chain."""
    supports = [set(model.supports[model.frames[f].parentJoint]) for f in frames]
    joints = sorted(supports[0] ^ supports[1])
    if any(model.nvs[j] != 1 for j in joints):
        raise ConfigError("a squeeze needs one-DoF joints between the two hands and their common body")
    before = np.array([[i in model.supports[j] for j in joints] for i in joints])
    return np.array([model.idx_vs[j] for j in joints], dtype=int), before
