"""Walking (paper Sec. III-A with Sec. IV-B's dataset): stand, accelerate, walk, decelerate, stand.

Phases come from `gait.plan_gait`: standing (both feet), then per step a double-support phase and
a single-support phase whose swing foot tracks cubic-spline references; the touchdown is an
impulse. Costs: swing-foot placement, base velocity (the commanded velocity), base orientation
(upright, heading), base height, centre-of-mass path, posture and torque regularization; the
builder adds friction and CoP cones on stance feet and joint-range penalties; Box-FDDP bounds the
torques. The solve strategy is in `trajopt.walk_strategy`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from opt2skill.data.record import Trajectory
from opt2skill.errors import SolverError
from opt2skill.trajopt.config import require
from opt2skill.trajopt.gait import Foothold, GaitPlan, swing_reference, yaw_matrix
from opt2skill.trajopt.task_params import TASK_PARAMS
from opt2skill.trajopt.phase_task import PhaseTask, Plan
from opt2skill.trajopt.phases import Contact, Knot, Phase, Problem
from opt2skill.trajopt.posture import Posture
from opt2skill.trajopt.receding import solve_receding
from opt2skill.trajopt.settings import ContactSettings, FeasibilityWeights, SolverSettings
from opt2skill.trajopt.solver import Solution
from opt2skill.trajopt.walk_gait import FEET, check_gait_timing, walk_gait
from opt2skill.trajopt.walk_strategy import RecedingSettings, StrideGuess

PARAMS = TASK_PARAMS["walk"]

BASE_SITE_KEY = "imu_site"


@dataclass(frozen=True)
class WalkWeights:
    swing: float = 1e5  # swing-foot placement (position and orientation) along its spline
    touchdown: float = 1e6  # foot placement at the impulse node
    base_velocity: float = 1e2  # world-frame base velocity: vx, vy, yaw rate
    vertical_velocity: float = 3.0  # relative weight of the base's vertical velocity (target 0): no bouncing
    base_orientation: float = 1e3  # upright, facing the heading
    base_height: float = 1e3
    com_path: float = 1e2  # CoM xy along the planned path

    def check(self) -> None:
        require(all(v >= 0 for v in vars(self).values()), "walk weights must be >= 0")


@dataclass(frozen=True)
class WalkThresholds:
    speed_error: float = 0.1  # m/s, |mean base speed over the cruise - requested|
    clearance_error: float = 0.03  # m, |median swing apex - requested|

    def check(self) -> None:
        require(self.speed_error > 0 and self.clearance_error > 0, "walk thresholds must be > 0")


@dataclass(frozen=True)
class WalkConfig:
    duration: float = 14.0  # s, the whole motion (the paper's dataset)
    steps: int = 0  # number of steps; 0: as many as fit in `duration`
    stand_start: float = 0.5  # s standing before the first step
    stand_end: float = 1.0  # s (at least) standing after the last step
    ramp: float = 1.5  # s to reach the commanded velocity, and to stop
    base_height: float = -0.03  # m, walking base height relative to standing, before `height_offset`
    weights: WalkWeights = field(default_factory=WalkWeights)
    posture: Posture = field(default_factory=lambda: Posture(base_orientation=0.0, base_velocity=0.0))
    contact: ContactSettings = field(default_factory=lambda: ContactSettings(min_normal_force=30.0))
    feasibility: FeasibilityWeights = field(default_factory=FeasibilityWeights)
    solver: SolverSettings = field(default_factory=lambda: SolverSettings(dt=0.03, max_iter=200, reg_init=1e-4))
    receding: RecedingSettings = field(default_factory=RecedingSettings)
    thresholds: WalkThresholds = field(default_factory=WalkThresholds)
    ranges: dict = field(default_factory=dict)  # parameter -> (low, high) sampling range

    def check(self) -> None:
        check_gait_timing(self)
        sections = (self.weights, self.posture, self.contact, self.feasibility, self.solver, self.receding, self.thresholds)
        for section in sections:
            section.check()


class WalkTask(PhaseTask):
    name = "walk"
    config_class = WalkConfig
    params = PARAMS
    _window: float | None = None  # the receding window of the solve under way, when it is the retry's

    def gait(self, params: dict[str, float]) -> tuple[GaitPlan, dict[str, Foothold]]:
        return walk_gait(self.robot, self.config, params)

    def plan(self, params: dict[str, float]) -> Plan:
        cfg, w = self.config, self.config.weights
        gait, feet = self.gait(params)
        x0 = np.concatenate([self.robot.stand_q_pin, np.zeros(self.robot.nv)])
        base_site = getattr(self.robot.config, BASE_SITE_KEY)
        base_z = x0[2] + cfg.base_height + params["height_offset"]
        posture = cfg.posture.weights(self.robot)
        clearance = params["clearance"]

        def contact(f: Foothold) -> Contact:
            return Contact(f.foot, pin.SE3(yaw_matrix(f.yaw), f.position))

        def tracking(knot: Knot, terms) -> list:
            com_xy, heading, velocity = gait.sample(knot.time)
            R = yaw_matrix(heading)
            out = [
                ("base_velocity", terms.velocity(base_site, [*velocity[:2], 0, 0, 0, velocity[2]], (1, 1, w.vertical_velocity, 0, 0, 1)), w.base_velocity),
                ("base_orientation", terms.rotation(base_site, R), w.base_orientation),
                ("base_height", terms.translation(base_site, [0, 0, base_z], (0, 0, 1)), w.base_height),
                ("com_path", terms.com([*com_xy, 0.0], (1, 1, 0)), w.com_path),
            ]
            return out + cfg.posture.terms(terms, x0, posture, knot.kind)

        def standing(knot: Knot, terms) -> list:
            return tracking(knot, terms)

        def swinging(step):
            def costs(knot: Knot, terms) -> list:
                out = tracking(knot, terms)
                site = self.robot.config.end_effectors[step.swing]
                if knot.kind == "impulse":
                    return cfg.posture.terms(terms, x0, posture, "impulse")
                if knot.kind == "terminal":
                    return out
                position, yaw, _ = swing_reference(step, knot.time, clearance)
                out.append(("swing", terms.placement(site, pin.SE3(yaw_matrix(yaw), position)), w.swing))
                return out

            return costs

        def landing(step):
            def costs(knot: Knot, terms) -> list:
                if knot.kind != "impulse":
                    return tracking(knot, terms)
                site = self.robot.config.end_effectors[step.swing]
                target = pin.SE3(yaw_matrix(step.target.yaw), step.target.position)
                return [("touchdown", terms.placement(site, target), w.touchdown)] + cfg.posture.terms(
                    terms, x0, posture, "impulse"
                )

            return costs

        stance = {name: feet[name] for name in FEET}
        phases = [Phase(gait.stand_start, tuple(contact(stance[n]) for n in FEET), standing, "stand")]
        for i, step in enumerate(gait.steps):
            both = tuple(contact(stance[n]) for n in FEET)
            if step.liftoff > step.start:
                phases.append(Phase(step.liftoff - step.start, both, landing(gait.steps[i - 1]) if i else standing, f"double {i}"))
            single = (contact(stance[step.stance]),)
            if step.liftoff == step.start and i:
                costs = _chain(landing(gait.steps[i - 1]), swinging(step))
            else:
                costs = swinging(step)
            phases.append(Phase(step.touchdown - step.liftoff, single, costs, f"swing {i} {step.swing}"))
            stance[step.swing] = step.target
        final = tuple(contact(stance[n]) for n in FEET)
        phases.append(Phase(gait.duration - gait.walk_end, final, landing(gait.steps[-1]), "stand"))
        return Plan(phases=phases, x0=x0, context=gait)

    def solve(self, params: dict[str, float], seed: int) -> Trajectory:
        """The walk; if its solve fails (`SolverError`), once more with `receding.retry_window`-long windows.

        Fast walks (1.4 to 1.5 m/s) can drift, window after window, into states no 1.4-s window
        recovers from; a longer look-ahead avoids it (docs/trajopt.md). The retry is recorded in
        `traj.solver["retry"]` and its time counts in `total_time`.
        """
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
        gait = plan.context
        return solve_receding(
            problem,
            self.config.solver,
            window=self._window or rc.window,
            commit=rc.commit,
            max_iter=rc.max_iter,
            first_max_iter=rc.first_max_iter,
            extend=StrideGuess(problem, gait),
        )

    def task_errors(self, traj: Trajectory) -> dict[str, dict[str, Any]]:
        from opt2skill.trajopt.walk_checks import walk_errors

        return walk_errors(self, traj)


def _chain(first, second):
    """Costs of a phase that starts with a touchdown impulse and continues as a swing."""

    def costs(knot: Knot, terms) -> list:
        return first(knot, terms) if knot.kind == "impulse" else second(knot, terms)

    return costs
