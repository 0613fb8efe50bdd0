"""Locomotion as a skill: a gait plan turned into phases, and the solve strategy walks need.

Phases: standing (both feet), then per step a double-support phase and a single-support phase whose
swing foot tracks its spline; the touchdown is an impulse with a placement cost. Costs: swing-foot
placement, base velocity (the commanded velocity), base orientation (upright, heading), base height
(following the support height on stairs), centre-of-mass path. Foot names come from the robot.
Tasks that walk (level walking, stairs, pickup then walk) compose these phases; `LocomotionTask`
gives them receding-window solves warm-started by the stride's periodicity, with one retry on
longer windows.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pinocchio as pin

from opt2skill.data.record import Trajectory
from opt2skill.errors import ConfigError, SolverError
from opt2skill.model.robot import Robot
from opt2skill.trajopt.config import require
from opt2skill.trajopt.phase_task import PhaseTask, Plan
from opt2skill.trajopt.phases import Contact, Knot, Phase, Problem
from opt2skill.trajopt.receding import solve_receding
from opt2skill.trajopt.skills.gait import Foothold, GaitPlan, Step, swing_reference, yaw_matrix
from opt2skill.trajopt.posture import Posture
from opt2skill.trajopt.settings import ContactSettings, SolverSettings
from opt2skill.trajopt.skills.stride_guess import RecedingSettings, StrideGuess
from opt2skill.trajopt.solver import Solution
from opt2skill.trajopt.task_config import TaskConfig

SwingReference = Callable[[Step, float, float], tuple[np.ndarray, float, np.ndarray]]


@dataclass(frozen=True)
class LocomotionWeights:
    swing: float = 1e5  # swing-foot placement (position and orientation) along its spline
    touchdown: float = 1e6  # foot placement at the impulse node
    base_velocity: float = 1e2  # world-frame base velocity: vx, vy, yaw rate
    vertical_velocity: float = 3.0  # relative weight of the base's vertical velocity (target: the support's)
    base_orientation: float = 1e3  # upright, facing the heading
    base_height: float = 1e3
    com_path: float = 1e2  # CoM xy along the planned path

    def check(self) -> None:
        require(all(v >= 0 for v in vars(self).values()), "locomotion weights must be >= 0")


@dataclass(frozen=True)
class LocomotionConfig(TaskConfig):
    """The config fields of every task that walks with this skill; a task adds its own."""

    stand_start: float = 0.5  # s standing before the first step
    stand_end: float = 1.0  # s (at least) standing after the last step
    ramp: float = 1.5  # s to reach the commanded velocity, and to stop
    base_height: float = -0.03  # m, walking base height relative to standing
    weights: LocomotionWeights = field(default_factory=LocomotionWeights)
    receding: RecedingSettings = field(default_factory=RecedingSettings)
    # Shared sections with walking's own defaults.
    posture: Posture = field(default_factory=lambda: Posture(base_orientation=0.0, base_velocity=0.0))
    contact: ContactSettings = field(default_factory=lambda: ContactSettings(min_normal_force=30.0))
    solver: SolverSettings = field(default_factory=lambda: SolverSettings(dt=0.03, max_iter=200, reg_init=1e-4))

    def check_own(self) -> None:
        require(self.stand_start >= 0.05 and self.stand_end >= 0.1, "stand_start >= 0.05 s and stand_end >= 0.1 s")
        require(self.ramp >= 0, "ramp must be >= 0 s")
        require(-0.2 <= self.base_height <= 0.05, "base_height must be in [-0.2, 0.05] m")
        for section in (self.weights, self.receding):
            section.check()


def stand_footholds(robot: Robot, q: np.ndarray) -> dict[str, Foothold]:
    """The robot's feet (sole centres) where configuration q puts them (left first), heading 0."""
    data = robot.pin_model.createData()
    pin.framesForwardKinematics(robot.pin_model, data, q)
    sole = {foot.name: robot.pin_frame_id(robot.config.end_effectors[foot.name]) for foot in robot.config.feet}
    return {name: Foothold(name, data.oMf[fid].translation.copy(), 0.0) for name, fid in sole.items()}


def com_xy(robot: Robot, q: np.ndarray) -> np.ndarray:
    """The centre of mass's horizontal position at configuration q."""
    return pin.centerOfMass(robot.pin_model, robot.pin_model.createData(), q)[:2].copy()


def foot_contact(foothold: Foothold) -> Contact:
    return Contact(foothold.foot, pin.SE3(yaw_matrix(foothold.yaw), foothold.position))


def locomotion_phases(
    robot: Robot,
    gait: GaitPlan,
    feet: dict[str, Foothold],
    weights: LocomotionWeights,
    base_z: float,
    clearance: float,
    swing: SwingReference = swing_reference,
    after: float = 0.0,
) -> list[Phase]:
    """Phases of the whole gait plan, from standing on `feet` to standing on the last footholds.

    `base_z`: the base (IMU site) height over level ground at the start; it follows the gait's
    support height (stairs). `after` (s): the phases start then, the task's own phases standing on
    `feet` before (pickup then walk); the first standing phase lasts `gait.stand_start - after`.
    Posture and torque terms are the task builder's, not added here."""
    w = weights
    base_site = robot.config.imu_site  # the base's pose is its IMU site's, as in the paper's rewards
    ee = robot.config.end_effectors
    dt_support = 1e-3  # s, for the support's vertical speed

    def tracking(knot: Knot, terms) -> list:
        com_xy, heading, velocity = gait.sample(knot.time)
        z = base_z + gait.support_height(knot.time)
        vz = (gait.support_height(knot.time + dt_support) - gait.support_height(knot.time - dt_support)) / (2 * dt_support)
        return [
            ("base_velocity", terms.velocity(base_site, [*velocity[:2], vz, 0, 0, velocity[2]], (1, 1, w.vertical_velocity, 0, 0, 1)), w.base_velocity),
            ("base_orientation", terms.rotation(base_site, yaw_matrix(heading)), w.base_orientation),
            ("base_height", terms.translation(base_site, [0, 0, z], (0, 0, 1)), w.base_height),
            ("com_path", terms.com([*com_xy, 0.0], (1, 1, 0)), w.com_path),
        ]

    def swinging(step: Step):
        def costs(knot: Knot, terms) -> list:
            if knot.kind == "impulse":
                return []
            out = tracking(knot, terms)
            if knot.kind == "terminal":
                return out
            position, yaw, _ = swing(step, knot.time, clearance)
            out.append(("swing", terms.placement(ee[step.swing], pin.SE3(yaw_matrix(yaw), position)), w.swing))
            return out

        return costs

    def landing(step: Step):
        def costs(knot: Knot, terms) -> list:
            if knot.kind != "impulse":
                return tracking(knot, terms)
            target = pin.SE3(yaw_matrix(step.target.yaw), step.target.position)
            return [("touchdown", terms.placement(ee[step.swing], target), w.touchdown)]

        return costs

    names = list(feet)
    stance = dict(feet)
    if not 0.0 <= after < gait.stand_start:
        raise ConfigError(f"the walk's phases start at {after:g} s, not before its first step ({gait.stand_start:g} s)")
    phases = [Phase(gait.stand_start - after, tuple(foot_contact(stance[n]) for n in names), tracking, "stand")]
    for i, step in enumerate(gait.steps):
        both = tuple(foot_contact(stance[n]) for n in names)
        if step.liftoff > step.start:
            phases.append(Phase(step.liftoff - step.start, both, landing(gait.steps[i - 1]) if i else tracking, f"double {i}"))
        single = (foot_contact(stance[step.stance]),)
        if step.liftoff == step.start and i:
            costs = _chain(landing(gait.steps[i - 1]), swinging(step))
        else:
            costs = swinging(step)
        phases.append(Phase(step.touchdown - step.liftoff, single, costs, f"swing {i} {step.swing}"))
        stance[step.swing] = step.target
    final = tuple(foot_contact(stance[n]) for n in names)
    phases.append(Phase(gait.duration - gait.walk_end, final, landing(gait.steps[-1]), "stand"))
    return phases


def _chain(first, second):
    """Costs of a phase that starts with a touchdown impulse and continues as a swing."""

    def costs(knot: Knot, terms) -> list:
        return first(knot, terms) if knot.kind == "impulse" else second(knot, terms)

    return costs


class LocomotionTask(PhaseTask):
    """A task whose plan walks (`plan.context` is its `GaitPlan`) and whose config has `receding`.

    Solved in receding windows warm-started by the stride's periodicity; a solve that fails
    (`SolverError`) runs once more with `receding.retry_window`-long windows: fast walks can drift,
    window after window, into states no 1.4-s window recovers from, and a longer look-ahead avoids
    it (docs/trajopt.md). The retry is recorded in `traj.solver["retry"]` and its time counts in
    `total_time`."""

    _window: float | None = None  # the receding window of the solve under way, when it is the retry's

    def solve(self, params: dict[str, float], seed: int) -> Trajectory:
        start = time.perf_counter()
        rc = self.config.receding
        try:
            return super().solve(params, seed)
        except SolverError as exc:
            if not (rc.enabled and rc.retry_window > rc.window):
                raise
            first_error = str(exc)
        self._window = rc.retry_window
        try:
            traj = super().solve(params, seed)
        except SolverError as exc:
            raise SolverError(f"{exc} (also with {rc.retry_window:g}-s windows; first attempt: {first_error})") from None
        finally:
            self._window = None
        traj.solver["retry"] = {"window": rc.retry_window, "first_error": first_error}
        traj.solver["total_time"] = time.perf_counter() - start
        return traj

    def optimize(self, problem: Problem, plan: Plan) -> Solution:
        rc = self.config.receding
        if not rc.enabled:
            return super().optimize(problem, plan)
        return solve_walk(problem, self.config.solver, rc, plan.context, self._window)


def solve_walk(problem: Problem, settings: SolverSettings, receding: RecedingSettings, gait: GaitPlan,
               window: float | None = None) -> Solution:
    """Receding windows for a problem that walks along `gait`: the nodes past a window's warm start
    begin as the node one stride earlier (`StrideGuess`). `receding`: the task's `RecedingSettings`;
    `window` replaces its window (the retry's)."""
    rc = receding
    return solve_receding(problem, settings, window=window or rc.window, commit=rc.commit, max_iter=rc.max_iter,
                          first_max_iter=rc.first_max_iter, extend=StrideGuess(problem, gait))
