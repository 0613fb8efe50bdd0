"""Stairs, up or down (paper Fig. 3 and Sec. IV's stair references): walk onto a flight of steps.

The scene is the flight (`scene.terrain.Stairs`): `n_steps` risers `step_height` apart, treads
`tread` deep, the first nosing `approach` m ahead of the start. The locomotion skill walks it: the
gait plan's footholds are moved onto the treads, the sole `edge_margin` clear of every nosing, at the
tread's height; the base follows the support height; each swing rises to `clearance` above the
higher foothold before it moves across (`stair_swing_reference`).

Checks (besides the dataset's physical and replay validation): the realized speed against the
plan's, every stance foot flat on one tread (corner heights against the ground under them), the
clearance between the swing sole and every nosing, and the height climbed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.scene.description import Scene
from opt2skill.scene.terrain import Stairs
from opt2skill.tasks import TaskInfo
from opt2skill.tasks.walk import speed_error
from opt2skill.trajopt.config import require
from opt2skill.trajopt.params import Param
from opt2skill.trajopt.phase_task import Plan
from opt2skill.trajopt.skills.gait import Foothold, GaitPlan, GaitSpec, on_frame_grid, plan_gait, stair_swing_reference
from opt2skill.trajopt.skills.locomotion import LocomotionConfig, LocomotionTask, com_xy, locomotion_phases, stand_footholds

PARAMS = (
    Param("step_height", allowed=(0.0, 0.15), default_range=(0.05, 0.15), unit="m", help="riser height"),
    Param("tread", allowed=(0.30, 0.50), default_range=(0.32, 0.40), unit="m", help="tread depth"),
    Param("n_steps", allowed=(1.0, 6.0), default_range=(2.0, 4.0), unit="", help="number of risers (rounded)"),
    Param("down", allowed=(0.0, 1.0), default_range=(0.0, 1.0), unit="", help="below 0.5: up; from 0.5: down"),
    Param("speed", allowed=(0.1, 0.6), default_range=(0.25, 0.4), unit="m/s", help="forward speed"),
    Param("step_duration", allowed=(0.35, 0.8), default_range=(0.45, 0.6), unit="s", help="one step (gait period / 2)"),
    Param("double_support", allowed=(0.1, 0.5), default_range=(0.2, 0.3), unit="", help="fraction of a step on both feet"),
    Param("clearance", allowed=(0.04, 0.2), default_range=(0.08, 0.12), unit="m", help="swing apex above the higher foothold"),
)


@dataclass(frozen=True)
class StairsThresholds:
    speed_error: float = 0.1  # m/s, |mean base speed - planned|
    flat_footing: float = 0.01  # m, largest |sole corner height - ground under it| at mid-stance
    nosing_clearance: float = 0.02  # m, the swing sole stays at least this far from every nosing
    climb_error: float = 0.03  # m, |base height change - (+/-) n_steps * step_height|

    def check(self) -> None:
        require(all(v > 0 for v in vars(self).values()), "stairs thresholds must be > 0")


@dataclass(frozen=True)
class StairsConfig(LocomotionConfig):
    approach: float = 0.55  # m from the stand pose's CoM to the first nosing
    beyond: float = 0.45  # m the CoM path goes past the last nosing
    edge_margin: float = 0.03  # m between a sole's toe or heel and a nosing
    ramp: float = 1.0  # s to reach the speed, and to stop (slower than level walking's)
    thresholds: StairsThresholds = field(default_factory=StairsThresholds)

    def check_own(self) -> None:
        super().check_own()
        require(0.3 <= self.approach <= 3.0, f"approach = {self.approach:g} m must be in [0.3, 3] m")
        require(0.3 <= self.beyond <= 3.0, f"beyond = {self.beyond:g} m must be in [0.3, 3] m")
        require(0.0 <= self.edge_margin <= 0.05, "edge_margin must be in [0, 0.05] m")
        self.thresholds.check()


class StairsTask(LocomotionTask):
    name = "stairs"
    config_class = StairsConfig
    params = PARAMS

    def scene(self, params: dict[str, float]) -> Scene:
        n = int(round(params["n_steps"]))
        com_x = float(com_xy(self.robot, self.robot.stand_q_pin)[0])
        start = com_x + self.config.approach
        if params["down"] >= 0.5:
            return Scene(Stairs(params["step_height"], params["tread"], start=start, n_steps=n,
                                landing=start + 1.5, down=True))
        return Scene(Stairs(params["step_height"], params["tread"], start=start, n_steps=n))

    def gait(self, params: dict[str, float]) -> tuple[GaitPlan, dict[str, Foothold], Scene]:
        cfg = self.config
        scene = self.scene(params)
        stairs = scene.terrain
        feet = stand_footholds(self.robot, self._start_q(scene))
        edges = nosings(stairs)
        distance = edges[-1] - float(com_xy(self.robot, self.robot.stand_q_pin)[0]) + cfg.beyond
        # Steps so that the CoM path (speed with smooth ramps) covers `distance`.
        step = on_frame_grid(params["step_duration"])
        ds = on_frame_grid(params["double_support"] * step)
        cruise = distance / params["speed"] + cfg.ramp
        n_steps = int(np.ceil((cruise + ds) / step)) + 1
        spec = GaitSpec(
            speed=params["speed"], lateral_speed=0.0, yaw_rate=0.0, clearance=params["clearance"],
            step_duration=params["step_duration"], double_support=params["double_support"],
            stand_start=cfg.stand_start, duration=cfg.stand_start + n_steps * step + cfg.stand_end,
            stand_end_min=cfg.stand_end, ramp=cfg.ramp, steps=n_steps,
        )
        half = max(foot.half_length for foot in self.robot.config.feet) + cfg.edge_margin
        sole_z = {name: f.position[2] - float(scene.ground_height(f.position[:2])) for name, f in feet.items()}

        def on_tread(foot: str, position: np.ndarray, yaw: float) -> np.ndarray:
            x = snap_between_nosings(float(position[0]), edges, half)
            z = float(scene.ground_height(np.array([x, position[1]]))) + sole_z[foot]
            return np.array([x, position[1], z])

        gait = plan_gait(spec, feet, com_xy(self.robot, self.robot.stand_q_pin), place=on_tread)
        return gait, feet, scene

    def _start_q(self, scene: Scene) -> np.ndarray:
        """The stand pose on the ground the robot starts on (the top landing when going down)."""
        q = self.robot.stand_q_pin.copy()
        q[2] += float(scene.ground_height(q[:2]))
        return q

    def plan(self, params: dict[str, float]) -> Plan:
        gait, feet, scene = self.gait(params)
        q0 = self._start_q(scene)
        x0 = np.concatenate([q0, np.zeros(self.robot.nv)])
        base_z = x0[2] + self.config.base_height
        phases = locomotion_phases(self.robot, gait, feet, self.config.weights, base_z, params["clearance"],
                                   swing=stair_swing_reference)
        return Plan(phases=phases, x0=x0, context=gait, scene=scene)

    def task_errors(self, traj: Trajectory) -> dict[str, dict[str, Any]]:
        th = self.config.thresholds
        gait, _, scene = self.gait(traj.params)
        corners = sole_corners(self.robot, traj.qpos)  # (T, feet, 4, 3)
        feet = [foot.name for foot in self.robot.config.feet]
        footing = 0.0
        for step in gait.steps:
            mid = int(round((step.touchdown + FRAME_DT * 20) / FRAME_DT))
            c = corners[min(mid, len(corners) - 1), feet.index(step.swing)]
            footing = max(footing, float(np.max(np.abs(c[:, 2] - scene.ground_height(c[:, :2])))))
        clearance = nosing_clearance(gait, corners, feet, scene)
        climb = float(scene.ground_height(traj.qpos[-1, :2]) - scene.ground_height(traj.qpos[0, :2]))
        climbed = float(traj.qpos[-1, 2] - traj.qpos[0, 2])
        return {
            "speed_error": {"value": speed_error(gait, traj), "limit": th.speed_error, "unit": "m/s"},
            "flat_footing": {"value": footing, "limit": th.flat_footing, "unit": "m"},
            "nosing_shortfall": {"value": max(0.0, th.nosing_clearance - clearance), "limit": 0.0, "unit": "m"},
            "nosing_clearance": {"value": clearance, "limit": None, "unit": "m"},
            "climb_error": {"value": abs(climbed - climb), "limit": th.climb_error, "unit": "m"},
        }


def nosings(stairs: Stairs) -> np.ndarray:
    """x of every nosing (step edge) of the flight, in order along +x."""
    return stairs.start + stairs.step_length * np.arange(stairs.n_steps)


def snap_between_nosings(x: float, edges: np.ndarray, half: float) -> float:
    """The nearest sole-centre x whose sole (half length `half`, margin included) spans no nosing."""
    if not np.any(np.abs(edges - x) < half):
        return x
    allowed = [(-np.inf, edges[0] - half)]
    allowed += [(a + half, b - half) for a, b in zip(edges[:-1], edges[1:]) if b - a >= 2 * half]
    allowed.append((edges[-1] + half, np.inf))
    candidates = [float(np.clip(x, lo, hi)) for lo, hi in allowed]
    return min(candidates, key=lambda c: abs(c - x))


def sole_corners(robot, qpos: np.ndarray) -> np.ndarray:
    """World positions (T, feet, 4, 3) of every foot's sole corners along a motion."""
    model = robot.mj_model
    data = mujoco.MjData(model)
    sites = [[robot.site_id(s) for s in foot.corner_sites] for foot in robot.config.feet]
    out = np.empty((len(qpos), len(sites), 4, 3))
    for t, q in enumerate(qpos):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        out[t] = data.site_xpos[sites]
    return out


def nosing_clearance(gait: GaitPlan, corners: np.ndarray, feet: list[str], scene: Scene) -> float:
    """Smallest distance (m), in the x-z plane, between a swinging sole (its heel-to-toe segment)
    and a nosing, from lift-off to touchdown; negative where the sole is below a nosing's top."""
    stairs = scene.terrain
    edges = nosings(stairs)
    tops = np.array([max(scene.ground_height(np.array([[x - 1e-6, 0.0], [x + 1e-6, 0.0]]))) for x in edges])
    best = np.inf
    for step in gait.steps:
        frames = slice(int(round(step.liftoff / FRAME_DT)) + 1, int(round(step.touchdown / FRAME_DT)))
        c = corners[frames, feet.index(step.swing)]  # (F, 4, 3)
        low = c[:, :, 2].min(axis=1)  # the sole as a segment at its lowest height, heel to toe
        heel = np.column_stack([c[:, :, 0].min(axis=1), low])
        toe = np.column_stack([c[:, :, 0].max(axis=1), low])
        for x, z in zip(edges, tops):
            d = _segment_distance(heel, toe, np.array([x, z]))
            over = (heel[:, 0] <= x) & (x <= toe[:, 0]) & (low < z)
            d[over] = -(z - low[over])
            best = min(best, float(d.min()))
    return best


def _segment_distance(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    ab = b - a
    s = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(a + s[:, None] * ab - p, axis=1)


def stairs_metrics(reference: Trajectory, tracked: Trajectory) -> dict[str, tuple[float, str]]:
    """Stair success: tracked to the reference's end (no fall) with the base within 5 cm of the
    reference's final height, i.e. standing on the level the reference ends on."""
    height_error = abs(float(tracked.qpos[-1, 2] - reference.qpos[-1, 2]))
    done = tracked.num_frames == reference.num_frames
    return {"stair_success": (float(done and height_error < 0.05), ""),
            "final_height_error": (100.0 * height_error, "cm")}


INFO = TaskInfo(
    name="stairs",
    summary="a flight of stairs up or down, footholds on the treads (paper Fig. 3)",
    task=StairsTask,
    params=PARAMS,
    demo_ranges={"step_height": (0.05, 0.10), "n_steps": (2.0, 2.0), "down": (0.0, 0.4)},
    metrics=stairs_metrics,
)
