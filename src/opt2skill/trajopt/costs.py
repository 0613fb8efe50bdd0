"""Cost terms for phase costs: small factories over Crocoddyl residuals, bound to one state and nu.

A task's cost function returns `(name, cost model, weight)` triples built with these; the same
factory works for running (nu = number of joints), impulse and terminal nodes (nu = 0 for impulses).
Sites are named as in the robot config (`robot.config.end_effectors` values, or any MJCF site).
"""

from __future__ import annotations

import functools

import crocoddyl
import numpy as np
import pinocchio as pin

from opt2skill.model.robot import Robot
from opt2skill.trajopt.native import load as load_native


def barrier(state, bounds: crocoddyl.ActivationBounds, residual):
    """A quadratic barrier outside `bounds` on a residual. Compiled where `trajopt.native` builds:
    inside the bounds (most nodes) it then skips the residual's derivatives, which Crocoddyl's cost
    computes only to multiply them by zero, and with a few rows outside it multiplies those rows
    alone; the results are Crocoddyl's to round-off."""
    activation = crocoddyl.ActivationModelQuadraticBarrier(bounds)
    native = load_native()
    if native is not None:
        return native.BarrierCostModel(state, activation, residual)
    return crocoddyl.CostModelResidual(state, activation, residual)


@functools.lru_cache(maxsize=64)
def _wrench_cone(mu: float, box: tuple[float, ...], min_normal: float):
    """A sole's wrench cone and its bounds, built once per shape: building one (its 17 rows) took
    about a fifth of a walk's problem build, every stance node asking for the same. Crocoddyl's
    residual and activation copy both, so the nodes share nothing through them."""
    cone = crocoddyl.WrenchCone(np.eye(3), mu, np.asarray(box), 4, True, min_normal)
    return cone, crocoddyl.ActivationBounds(cone.lb, cone.ub)


class Terms:
    def __init__(self, state: crocoddyl.StateMultibody, nu: int, robot: Robot):
        self.state = state
        self.nu = nu
        self.robot = robot

    def _site(self, site: str) -> int:
        return self.robot.pin_frame_id(site)

    @staticmethod
    def _weighted(residual, weights) -> crocoddyl.CostModelResidual:
        weights = np.asarray(weights, dtype=float)
        return crocoddyl.CostModelResidual(residual.state, crocoddyl.ActivationModelWeightedQuad(weights**2), residual)

    # -- regularization ------------------------------------------------------------------------

    def state_reg(self, x_ref: np.ndarray, weights: np.ndarray):
        """sum (w_i (x - x_ref)_i)^2 over the state tangent (ndx = 2 nv)."""
        return self._weighted(crocoddyl.ResidualModelState(self.state, np.asarray(x_ref, float), self.nu), weights)

    def control_reg(self, weights: np.ndarray | float, u_ref: np.ndarray | None = None):
        u_ref = np.zeros(self.nu) if u_ref is None else np.asarray(u_ref, float)
        residual = crocoddyl.ResidualModelControl(self.state, u_ref)
        return self._weighted(residual, np.broadcast_to(weights, (self.nu,)))

    def acceleration(self, weights: np.ndarray | float):
        """sum (w_i a_i)^2 over the generalized accelerations (running nodes: the dynamics' output)."""
        nv = self.state.nv
        residual = crocoddyl.ResidualModelJointAcceleration(self.state, np.zeros(nv), self.nu)
        return self._weighted(residual, np.broadcast_to(weights, (nv,)))

    def state_bounds(self, lb: np.ndarray, ub: np.ndarray):
        """Quadratic barrier outside [lb, ub] on x - x_neutral (joint ranges and speed limits)."""
        pm = self.state.pinocchio
        x_neutral = np.concatenate([pin.neutral(pm), np.zeros(pm.nv)])
        residual = crocoddyl.ResidualModelState(self.state, x_neutral, self.nu)
        return barrier(self.state, crocoddyl.ActivationBounds(lb, ub), residual)

    # -- task space ----------------------------------------------------------------------------

    def placement(self, site: str, target: pin.SE3, weights=(1, 1, 1, 1, 1, 1)):
        """Position and orientation of a site (residual log6 of the error, local axes)."""
        residual = crocoddyl.ResidualModelFramePlacement(self.state, self._site(site), target, self.nu)
        return self._weighted(residual, weights)

    def translation(self, site: str, target: np.ndarray, weights=(1, 1, 1)):
        residual = crocoddyl.ResidualModelFrameTranslation(self.state, self._site(site), np.asarray(target, float), self.nu)
        return self._weighted(residual, weights)

    def above(self, site: str, height: float):
        """Zero while a site is at least `height` m high; quadratic in the shortfall below it (a
        barrier that keeps an arm off a desk top the optimizer does not otherwise see)."""
        residual = crocoddyl.ResidualModelFrameTranslation(self.state, self._site(site), np.zeros(3), self.nu)
        bounds = crocoddyl.ActivationBounds(np.array([-np.inf, -np.inf, height]), np.full(3, np.inf))
        return barrier(self.state, bounds, residual)

    def rotation(self, site: str, target: np.ndarray, weights=(1, 1, 1)):
        residual = crocoddyl.ResidualModelFrameRotation(self.state, self._site(site), np.asarray(target, float), self.nu)
        return self._weighted(residual, weights)

    def velocity(self, site: str, target: np.ndarray, weights=(1, 1, 1, 1, 1, 1), frame=pin.LOCAL_WORLD_ALIGNED):
        """Spatial velocity (linear, angular) of a site, by default in world-aligned axes."""
        motion = pin.Motion(np.asarray(target, float))
        residual = crocoddyl.ResidualModelFrameVelocity(self.state, self._site(site), motion, frame, self.nu)
        return self._weighted(residual, weights)

    def com(self, target: np.ndarray, weights=(1, 1, 1)):
        residual = crocoddyl.ResidualModelCoMPosition(self.state, np.asarray(target, float), self.nu)
        return self._weighted(residual, weights)

    # -- contact forces ------------------------------------------------------------------------

    def wrench_cone(self, frame_id: int, mu: float, box: np.ndarray, min_normal: float):
        """Friction, centre of pressure and yaw torque of a flat contact (forces in its LOCAL frame)."""
        cone, bounds = _wrench_cone(float(mu), tuple(np.asarray(box, float).tolist()), float(min_normal))
        residual = crocoddyl.ResidualModelContactWrenchCone(self.state, frame_id, cone, self.nu, True)
        return barrier(self.state, bounds, residual)

    def friction_cone(self, frame_id: int, surface: np.ndarray, mu: float, min_normal: float):
        """Coulomb cone of a point contact; `surface`'s z axis is the normal (world-aligned forces)."""
        cone = crocoddyl.FrictionCone(np.asarray(surface, float), mu, 4, True, min_normal)
        residual = crocoddyl.ResidualModelContactFrictionCone(self.state, frame_id, cone, self.nu, True)
        return barrier(self.state, crocoddyl.ActivationBounds(cone.lb, cone.ub), residual)

    def contact_force(self, frame_id: int, wrench: np.ndarray, weights):
        """Track a contact force (e.g. a wiping force); `wrench` in the contact's force coordinates."""
        wrench = np.asarray(wrench, float)
        force = pin.Force(wrench) if len(wrench) == 6 else pin.Force(np.concatenate([wrench, np.zeros(3)]))
        residual = crocoddyl.ResidualModelContactForce(self.state, frame_id, force, len(wrench), self.nu, True)
        return self._weighted(residual, weights)
