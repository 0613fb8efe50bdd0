"""The pipeline every phase-based task shares: plan -> problem -> Box-FDDP -> 200 Hz frames -> record.

A task subclass supplies its config (a `TaskConfig`), its parameters and `plan(params)` (phases with
the task's own costs, start state, scene, optional initial guess); it may replace `optimize` with its
own solve strategy. The standard costs every node gets (state and torque regularization towards the
plan's posture, with the config's weights or the phase's own, heavier on the terminal node) are added here, not by each task; the builder adds
the physical limits (cones, joint ranges, torque bounds).
"""

from __future__ import annotations

import dataclasses
import time
from abc import abstractmethod
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

import numpy as np

from opt2skill.data.record import Trajectory
from opt2skill.errors import SolverError
from opt2skill.model.robot import Robot
from opt2skill.provenance import provenance
from opt2skill.scene.description import Scene
from opt2skill.trajopt import frames as frames_mod
from opt2skill.trajopt.config import apply_overrides, config_to_dict
from opt2skill.trajopt.extract import knots, to_trajectory
from opt2skill.trajopt.integrator import implementation
from opt2skill.trajopt.params import Param, ParamSpace
from opt2skill.trajopt.phases import Phase, Problem, ProblemBuilder
from opt2skill.trajopt.solver import Solution, riccati_gains, solve, solver_implementation
from opt2skill.trajopt.task import Task
from opt2skill.trajopt.tracking import track


@dataclass
class Plan:
    phases: list[Phase]
    x0: np.ndarray  # start state, Pinocchio layout
    guess: Callable[[Problem], list[np.ndarray]] | None = None  # initial states for a built problem
    context: Any = None  # what the task's own solve strategy needs (e.g. the gait plan)
    scene: Scene = field(default_factory=Scene)  # what the motion is made on; stored in the record
    posture: np.ndarray | None = None  # the regularization's reference state (default: x0)


class PhaseTask(Task):
    """A task whose config is a `TaskConfig` (posture, contact, feasibility, solver, ranges)."""

    config_class: ClassVar[type]
    params: ClassVar[tuple[Param, ...]]

    def __init__(self, robot: Robot, overrides: dict[str, Any] | None = None):
        super().__init__(robot, overrides)
        self.config = apply_overrides(self.config_class(), overrides)
        self.builder = ProblemBuilder(robot, self.config.contact, self.config.feasibility)
        self.param_space()  # bad sampling ranges fail here, not in a worker later

    def param_space(self) -> ParamSpace:
        return ParamSpace(list(self.params), ranges=self.config.ranges)

    @abstractmethod
    def plan(self, params: dict[str, float]) -> Plan:
        """Phases, start state and optional guess for checked parameters."""

    def optimize(self, problem: Problem, plan: Plan) -> Solution:
        """The solve strategy (default: one Box-FDDP solve from the plan's guess)."""
        xs = plan.guess(problem) if plan.guess else None
        return solve(problem, self.config.solver, xs)

    def solve(self, params: dict[str, float], seed: int) -> Trajectory:
        start = time.perf_counter()
        params = self.param_space().check(params)
        plan = self.plan(params)
        settings = self.config.solver
        phases = self._with_standard_costs(plan)
        problem = self.builder.build(phases, plan.x0, settings.dt, integrator=settings.integrator)
        solution = self.optimize(problem, plan)
        if settings.keep_gains and settings.gains == "riccati":
            gains = riccati_gains(problem.shooting, solution.xs, solution.us, settings.gains_regularization)
            solution = dataclasses.replace(solution, K=gains)
        solver_knots = knots(problem, solution, settings.keep_gains)  # before the rollout moves contacts
        if settings.completion == "track":
            frames = track(problem, solution, self._cones(problem), settings.track_bandwidth)
        elif settings.completion == "rollout":
            frames = frames_mod.rollout(problem, solution, self._cones(problem))
        else:
            frames = frames_mod.interpolate(problem, solution)
        frames = self.complete_frames(plan, problem, frames, solver_knots)
        if not (np.all(np.isfinite(frames.q)) and np.all(np.isfinite(frames.v)) and np.all(np.isfinite(frames.wrench))):
            raise SolverError(
                f"task '{self.name}': the 200 Hz frames diverged ({solution.stop_reason}, cost {solution.cost:.3g})"
            )
        solver_stats = {
            "name": "BoxFDDP",
            "iterations": solution.iterations,
            "converged": solution.converged,
            "stop_reason": solution.stop_reason,
            "cost": solution.cost,
            "dynamic_gap": solution.gap,
            "solve_time": solution.seconds,
            "total_time": 0.0,
            "dt": settings.dt,
            "nodes": len(problem.nodes),
            "completion": settings.completion,
            # which matched integrator ran: the two agree to round-off, not bitwise (trajopt.native)
            "integrator": settings.integrator + (f" ({implementation()})" if settings.integrator == "matched" else ""),
            "solver_parts": solver_implementation(),  # avx2-fma or crocoddyl: likewise round-off apart
            **self.solver_extras(),
        }
        traj = to_trajectory(
            self.robot,
            frames,
            problem,
            task=self.name,
            params=params,
            seed=seed,
            solver=solver_stats,
            provenance=provenance(self.robot.hash, task_config=config_to_dict(self.config)),
            knots=solver_knots,
            scene=plan.scene,
        )
        traj.solver["total_time"] = time.perf_counter() - start
        return traj

    def complete_frames(self, plan: Plan, problem: Problem, frames: frames_mod.Frames, knots: dict) -> frames_mod.Frames:
        """What the record needs beyond the optimizer's own frames and knots (e.g. a carried object's
        forces on the hands, filled in place); default: the frames as they are."""
        return frames

    def _with_standard_costs(self, plan: Plan) -> list[Phase]:
        """The plan's phases, each node's task costs followed by the posture and torque terms."""
        reference = plan.x0 if plan.posture is None else plan.posture

        def standard(costs, posture):
            weights = posture.weights(self.robot)

            def all_costs(knot, terms) -> list:
                return list(costs(knot, terms)) + posture.terms(terms, reference, weights, knot.kind)

            return all_costs

        return [dataclasses.replace(phase, costs=standard(phase.costs, phase.posture or self.config.posture))
                for phase in plan.phases]

    def _cones(self, problem: Problem) -> frames_mod.ContactCones:
        """The contact cones a rollout keeps the 200 Hz wrenches in: the robot's friction and soles,
        shrunk by `contact.frame_cone_scale` so rounding stays inside the validated cones."""
        scale = self.config.contact.frame_cone_scale
        feet = {}
        for name in problem.contact_names:
            if problem.flat[name]:
                foot = self.builder._foot(name)
                feet[name] = (2 * foot.half_length * scale, 2 * foot.half_width * scale)
        return frames_mod.ContactCones(problem, feet, self.robot.config.friction_coefficient * scale)

    def solver_extras(self) -> dict[str, Any]:
        """More solver statistics a strategy wants recorded (e.g. warm-start iterations)."""
        return {}
