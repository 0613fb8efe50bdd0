"""Config sections every task shares: contact model, feasibility weights, solver. Task configs embed them."""

from __future__ import annotations

from dataclasses import dataclass

from opt2skill.data.record import FRAME_DT
from opt2skill.trajopt.config import require

COMPLETIONS = ("track", "rollout", "interpolate")
GAINS = ("solver", "riccati")
INTEGRATORS = ("euler", "matched", "rk2", "rk3", "rk4")


@dataclass(frozen=True)
class ContactSettings:
    """Rigid contacts: Baumgarte gains, friction and centre-of-pressure margins, impacts."""

    baumgarte_kp: float = 100.0  # position term, referenced to the planned contact placement (pitfalls.md)
    baumgarte_kd: float = 20.0
    friction_scale: float = 0.8  # the optimizer's cone uses mu * this (the robot's mu is checked afterwards)
    cop_scale: float = 0.8  # the optimizer's CoP box is this fraction of the sole
    min_normal_force: float = 10.0  # N, per stance foot, inside the optimizer's cone
    impacts: bool = True  # an impulse node where a contact starts
    impacts_hold: bool = True  # ... with the fixed contacts that continue through it (docs/trajopt.md)
    frame_cone_scale: float = 0.97  # the 200 Hz rollout keeps wrenches inside cones shrunk by this

    def check(self) -> None:
        require(self.baumgarte_kp >= 0 and self.baumgarte_kd >= 0, "contact.baumgarte_kp/kd must be >= 0")
        require(0 < self.friction_scale <= 1, "contact.friction_scale must be in (0, 1]")
        require(0 < self.cop_scale <= 1, "contact.cop_scale must be in (0, 1]")
        require(self.min_normal_force >= 0, "contact.min_normal_force must be >= 0 N")


@dataclass(frozen=True)
class FeasibilityWeights:
    """Penalty weights of the physical limits FDDP cannot impose as hard constraints."""

    wrench_cone: float = 1e3  # friction cone and CoP of every stance contact (pitfalls: 10 is too weak)
    joint_limits: float = 1e4  # joint position and velocity ranges
    joint_limit_margin: float = 0.03  # rad: the optimizer's ranges are this much inside the model's
    velocity_limit_scale: float = 0.9  # the optimizer's speed limits are this fraction of the model's
    torque_limit_scale: float = 0.85  # Box-FDDP's torque bounds; the rest is left for feedback at 200 Hz

    def check(self) -> None:
        require(self.wrench_cone >= 0 and self.joint_limits >= 0, "feasibility weights must be >= 0")
        require(0 <= self.joint_limit_margin < 0.2, "feasibility.joint_limit_margin must be in [0, 0.2) rad")
        require(0 < self.velocity_limit_scale <= 1, "feasibility.velocity_limit_scale must be in (0, 1]")
        require(0 < self.torque_limit_scale <= 1, "feasibility.torque_limit_scale must be in (0, 1]")


@dataclass(frozen=True)
class SolverSettings:
    """Box-FDDP on a coarse grid, then 200 Hz frames (docs/trajopt.md)."""

    dt: float = 0.02  # s, the optimization grid; a multiple of the 200 Hz frame period
    integrator: str = "matched"  # semi-implicit Euler with the 200 Hz frames' position update (trajopt.integrator),
    # "euler" (Crocoddyl's semi-implicit Euler) or Runge-Kutta "rk2", "rk3", "rk4"
    max_iter: int = 200
    stop: float = 1e-7  # Crocoddyl's stopping criterion
    stall_window: int = 3  # stop when the cost fell less than `stall_tol` (relative) over this many iterations
    stall_tol: float = 1e-3
    reg_init: float = 1e-9
    line_search_steps: int = 10  # step lengths tried: 1, 1/2, ..., 2^-(n-1)
    # A step no longer than this raises the regularization, as a failed line search does (Crocoddyl's
    # th_stepInc). 0.2 takes 12 to 16 % of a walk's solver work, with somewhat worse plans on a few
    # walks (docs/trajopt.md, "Speed: the solver's own levers"); the walk's default is 0.1.
    reg_increase_below: float = 0.01
    # A trial step is accepted when the cost falls by at least this fraction of the decrease the
    # quadratic model predicts for it (Crocoddyl's th_acceptStep, an Armijo condition); 0.1 is Crocoddyl's.
    accept_step: float = 0.1
    # Receding windows: a window's solve also ends, once its gaps are closed, when a full step moved no
    # state of the part it commits by more than this (max abs over the committed nodes' states): the
    # part beyond the commit is solved again by the next window. 0: off (docs/trajopt.md).
    commit_tol: float = 0.0
    completion: str = "track"  # 200 Hz frames: "track" (acceleration tracking, exact), "rollout" (feedback law) or "interpolate"
    track_bandwidth: float = 30.0  # rad/s, the PD of the "track" completion (Kp = bandwidth^2, Kd = 2 bandwidth)
    keep_gains: bool = False  # store the feedback gains K with the knots (traj.knots)
    # The feedback expert's gains: "solver" keeps each receding window's own Riccati gains; "riccati"
    # recomputes them in one backward pass over the whole motion at the solution, with Quu and Vxx
    # regularized by `gains_regularization` (softer feedback, no gains inflated by a window's end).
    gains: str = "solver"
    gains_regularization: float = 1e-2

    def check(self) -> None:
        steps = self.dt / FRAME_DT
        require(
            self.dt > 0 and abs(steps - round(steps)) < 1e-9,
            f"solver.dt = {self.dt:g} s must be a positive multiple of the frame period {FRAME_DT:g} s",
        )
        require(self.max_iter >= 1, "solver.max_iter must be >= 1")
        require(1 <= self.line_search_steps <= 20, "solver.line_search_steps must be in [1, 20]")
        require(0 < self.reg_increase_below < 0.5, "solver.reg_increase_below must be in (0, 0.5): longer steps lower the regularization")
        require(0 <= self.accept_step < 1, "solver.accept_step must be in [0, 1): the share of the predicted decrease a step must reach")
        require(self.stop > 0, "solver.stop must be > 0")
        require(self.commit_tol >= 0, "solver.commit_tol must be >= 0 (0: off)")
        require(self.stall_window >= 1 and self.stall_tol >= 0, "solver.stall_window >= 1 and stall_tol >= 0")
        require(self.integrator in INTEGRATORS, f"solver.integrator must be one of {INTEGRATORS}, got '{self.integrator}'")
        require(self.track_bandwidth > 0, "solver.track_bandwidth must be > 0 rad/s")
        require(self.gains in GAINS, f"solver.gains must be one of {GAINS}, got '{self.gains}'")
        require(self.gains_regularization >= 0, "solver.gains_regularization must be >= 0")
        require(self.completion in COMPLETIONS, f"solver.completion must be one of {COMPLETIONS}, got '{self.completion}'")
