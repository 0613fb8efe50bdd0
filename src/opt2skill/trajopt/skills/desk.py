"""Standing at a desk as a skill: the desk in front of the stand pose, the feet held on their stand
footholds, and the costs of a standing manipulation phase (hands along their paths, the CoM over
the feet, an upright torso). The wiping and desk-reach tasks compose their phases from these."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from opt2skill.errors import ConfigError
from opt2skill.model.robot import Robot
from opt2skill.scene.description import Scene
from opt2skill.scene.props import Desk
from opt2skill.trajopt.config import require
from opt2skill.trajopt.phase_task import Plan, PhaseTask
from opt2skill.trajopt.phases import Contact, Knot, Problem
from opt2skill.trajopt.receding import solve_standing
from opt2skill.trajopt.settings import SolverSettings
from opt2skill.trajopt.solver import Solution
from opt2skill.trajopt.skills.stride_guess import RecedingSettings
from opt2skill.trajopt.task_config import TaskConfig
from opt2skill.trajopt.skills.locomotion import foot_contact, stand_footholds
from opt2skill.trajopt.skills.manipulation import HandPath, end_effector_positions


@dataclass(frozen=True)
class Stand:
    """The stand pose: start state, feet contacts, the middle of the feet, end effectors' positions."""

    x0: np.ndarray
    feet: tuple[Contact, ...]
    centre: np.ndarray
    home: dict[str, np.ndarray]

    @classmethod
    def of(cls, robot: Robot) -> Stand:
        q0 = robot.stand_q_pin
        feet = tuple(foot_contact(f) for f in stand_footholds(robot, q0).values())
        centre = np.mean([c.placement.translation for c in feet], axis=0)
        return cls(np.concatenate([q0, np.zeros(robot.nv)]), feet, centre,
                   end_effector_positions(robot, q0, list(robot.config.end_effectors)))


@dataclass(frozen=True)
class DeskConfig(TaskConfig):
    """The config fields of every task at a desk; a task adds its own."""

    desk_depth: float = 0.6  # m, along x
    desk_width: float = 1.2  # m
    desk_gap: float = 0.25  # m from the base to the desk's front edge (the hands at home stay in front of it)
    desk_friction: float = 1.0
    reachable: tuple[float, float] = (0.8, 1.0)  # m, the desk tops the task can be done at (docs/trajopt.md)
    # windows of 2 s (1.4-s windows of 20 iterations left the feet's forces chattering at the seams)
    receding: RecedingSettings = field(default_factory=lambda: RecedingSettings(
        window=2.0, commit=1.0, max_iter=40, first_max_iter=80, retry_window=0.0))
    solver: SolverSettings = field(default_factory=lambda: SolverSettings(dt=0.02, max_iter=200, reg_init=1e-4))

    def check_own(self) -> None:
        require(0.5 <= self.reachable[0] < self.reachable[1] <= 1.5, "reachable must be an increasing pair in [0.5, 1.5] m")
        require(0.05 <= self.desk_gap <= 0.5, "desk_gap must be in [0.05, 0.5] m")
        require(0.05 <= self.desk_friction <= 3.0, "desk_friction must be in [0.05, 3]")
        self.receding.check()


class DeskTask(PhaseTask):
    """A task standing at a desk whose top is at the parameter `desk_height` (config: `DeskConfig`),
    solved in receding windows each warm-started by holding the last state."""

    doing: str = "do the task"  # for the message of an unreachable desk

    def check_reach(self, params: dict[str, float]) -> None:
        lo, hi = self.config.reachable
        if not lo <= params["desk_height"] <= hi:
            raise ConfigError(f"desk_height = {params['desk_height']:g} m: the robot cannot {self.doing} at that desk "
                              f"top standing; reachable desk heights are [{lo:g}, {hi:g}] m")

    def scene(self, params: dict[str, float]) -> Scene:
        """The desk in front of the stand pose: its front edge `desk_gap` m ahead of the base."""
        cfg, base = self.config, self.robot.stand_q_pin
        return Scene(props=(Desk(pos=(base[0] + cfg.desk_gap + cfg.desk_depth / 2, base[1]), height=params["desk_height"],
                                 width=cfg.desk_width, depth=cfg.desk_depth, friction=cfg.desk_friction),))

    def optimize(self, problem: Problem, plan: Plan) -> Solution:
        rc = self.config.receding
        if not rc.enabled:
            return super().optimize(problem, plan)
        return solve_standing(problem, self.config.solver, rc)


@dataclass(frozen=True)
class StandingCosts:
    """Cost builders of a standing phase; weights: CoM over the feet (x, y), torso upright, paths,
    and the feet's wrenches towards half the robot's weight each, centred on the soles (`feet`):
    two flat feet leave their split free, and a solve capped at a few iterations per window let it
    swing between the feet from one node to the next, which no controller in MuJoCo follows."""

    robot: Robot
    stand: Stand
    com: float
    upright: float
    paths: float
    feet: float = 0.0

    def balance(self, terms, com: float | None = None, upright: float | None = None) -> list:
        """The CoM over the feet, the torso upright and (running nodes) the feet's split."""
        c = self.stand.centre
        shares = self.feet_forces(terms) if self.feet > 0 and terms.nu > 0 else []
        return shares + [("com", terms.com([c[0], c[1], 0.0], (1, 1, 0)), self.com if com is None else com),
                ("base_orientation", terms.rotation(self.robot.config.imu_site, np.eye(3)),
                 self.upright if upright is None else upright)]

    def feet_forces(self, terms) -> list:
        half = pin.computeTotalMass(self.robot.pin_model) * 9.81 / 2
        wrench = np.array([0.0, 0.0, half, 0.0, 0.0, 0.0])  # a stand foot's frame is the world's, up to yaw
        return [(f"{c.name}_share", terms.contact_force(self.robot.pin_frame_id(self.robot.config.end_effectors[c.name]),
                                                        wrench, np.ones(6)), self.feet) for c in self.stand.feet]

    def along(self, terms, knot: Knot, path: HandPath, names, weight: float | None = None) -> list:
        """End effectors `names` at their targets on `path` at the knot's time."""
        sites = self.robot.config.end_effectors
        return [(f"{n}_path", terms.translation(sites[n], p), self.paths if weight is None else weight)
                for n, p in path.at(knot.time).items() if n in names]
