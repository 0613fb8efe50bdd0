"""200 Hz frames that follow the coarse plan: acceleration tracking on the optimizer's own dynamics.

Each coarse running node k holds the plan's acceleration a_k = (v_{k+1} - v_k) / dt. Its frames are
5-ms semi-implicit Euler steps of the node's own contact dynamics (the same differential model,
contacts and Baumgarte terms) with the torque, at each frame, that best produces

    a_des = a_k + Kp (q_ref (-) q) + Kd (v_ref - v)

in the kinetic-energy metric (least squares ||a(u) - a_des||_M: a(u) is affine in u at a given state;
the map Fu = da/du and M are taken at the node's first frame, which halves the cost and changes the
frames by 1e-4 rad), where (q_ref, v_ref) are 5-ms Euler steps from the knot with a_k
held. With the plan integrated by `integrator.MatchedEulerModel`, those reference steps land on the
next knot, so an exact frame stays on the plan and the PD term only removes what the contact
constraint and the free-flyer's manifold make differ. `frames.complete` does the rest: torques
clipped to the limits, wrenches kept in their cones, impulses at their instants, touching-down
contacts held where the foot is.

Every frame is therefore an exact step of the optimizer's dynamics (inverse-dynamics residual at
rounding level except the step into a touchdown). Measured on 16 14-s walks up to 1.34 m/s, at the
knots the frames are within 0.0001 to 0.015 rad and 0.003 to 0.5 rad/s of the plan's joints and 4 mm
of its base, where a rollout of the solver's feedback law on a semi-implicit Euler plan left it by
0.06 to 0.14 rad and 1 to 1.9 rad/s, pushed joint speeds past their limits on fast walks, and
diverged on some (docs/trajopt.md).
"""

from __future__ import annotations

import functools

import numpy as np

from opt2skill.data.record import FRAME_DT
from opt2skill.trajopt.frames import ContactCones, Frames, NodePolicy, complete
from opt2skill.trajopt.phases import Problem
from opt2skill.trajopt.solver import Solution


def track(coarse: Problem, solution: Solution, cones: ContactCones | None, bandwidth: float) -> Frames:
    """Frames at 5 ms following `solution` on `coarse`'s dynamics (`frames.complete`); `bandwidth`
    (rad/s) sets the PD: Kp = bandwidth^2, Kd = 2 bandwidth (critically damped)."""
    state = coarse.shooting.runningModels[0].state
    kp, kd = bandwidth**2, 2.0 * bandwidth
    xs, us = solution.xs, solution.us

    def policy_for_node(k: int, fine, fine_data) -> NodePolicy:
        return NodeTracking(state, fine, fine_data, xs[k], xs[k + 1], us[k], coarse.nodes[k].dt, kp, kd)

    return complete(coarse, cones, policy_for_node)


class NodeTracking:
    """The tracking law over one coarse node (the module's docstring), frame by frame: called with
    (frame index within the node, state) it gives the frame's torque. `frames.complete` runs it in
    C++ where the compiled parts load (`compiled_law`, `native/frame_tracking.hpp`: the same law and
    order of terms), else through these calls; the two agree to round-off (tests/test_trajopt_native.py)."""

    def __init__(self, state, fine, fine_data, x_k: np.ndarray, x_next: np.ndarray, u_k: np.ndarray, dt: float,
                 kp: float, kd: float):
        nq, nv = state.nq, state.nv
        self.state, self.fine, self.fine_data, self.kp, self.kd = state, fine, fine_data, kp, kd
        self.u_k = np.ascontiguousarray(u_k, dtype=float)
        self.a_plan = (x_next[nq:] - x_k[nq:]) / dt
        self.step = np.concatenate([np.zeros(nv), self.a_plan * FRAME_DT])  # 5-ms Euler step with a_plan held
        self.x_ref = np.array(x_k, dtype=float)  # the reference at the current frame, stepped in place
        self.gain: np.ndarray | None = None

    def start(self, x: np.ndarray) -> None:
        """The torque-to-acceleration map of the node's first frame (feedback needs it roughly), at
        the node's first state `x`; leaves the node's data evaluated at (x, u_k)."""
        self.fine.calc(self.fine_data, x, self.u_k)
        self.fine.calcDiff(self.fine_data, x, self.u_k)
        self.gain = _least_squares_gain(self.fine_data.differential)

    def __call__(self, i: int, x: np.ndarray) -> np.ndarray:
        nq, nv = self.state.nq, self.state.nv
        if i > 0:
            self.step[:nv] = self.x_ref[nq:] * FRAME_DT + self.a_plan * FRAME_DT**2
            self.x_ref[:] = self.state.integrate(self.x_ref, self.step)
        error = self.state.diff(x, self.x_ref)  # x_ref (-) x
        a_des = self.a_plan + self.kp * error[:nv] + self.kd * error[nv:]
        if i == 0:
            self.start(x)
        else:
            self.fine.calc(self.fine_data, x, self.u_k)
        return self.u_k + self.gain @ (a_des - self.fine_data.differential.xout)

    def compiled_law(self) -> dict:
        """What the compiled loop needs; it computes the gain itself (`start`'s, without the node's other
        derivatives) at the node's first frame into `gain`."""
        self.gain = np.empty((len(self.u_k), self.state.nv))
        return {"state": self.state, "kp": self.kp, "kd": self.kd, "x_ref": self.x_ref, "u_k": self.u_k,
                "a_plan": np.ascontiguousarray(self.a_plan), "gain": self.gain}


@functools.cache
def _lower_triangle(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.tril_indices(n, -1)


def _least_squares_gain(dynamics_data) -> np.ndarray:
    """G with du = G (a_des - a) minimizing ||a + Fu du - a_des||_M (Fu = da/du, M the joint-space
    inertia, both at the data's state)."""
    fu = dynamics_data.Fu
    mass = np.array(dynamics_data.multibody.pinocchio.M)  # Pinocchio fills the upper triangle
    lower = _lower_triangle(len(mass))
    mass[lower] = mass.T[lower]
    weighted = fu.T @ mass
    hessian = weighted @ fu
    hessian.flat[:: hessian.shape[0] + 1] += 1e-9 * np.trace(hessian)
    return np.linalg.solve(hessian, weighted)
