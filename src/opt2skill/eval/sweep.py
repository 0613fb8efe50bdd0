"""Terrain sweeps (Section IV-B, Fig. 3): success rate on stairs of growing step height and slopes of
growing angle, ten trials per setting with the initial yaw uniform in [-25, 25] degrees.

Set-up (docs/eval.md, "Terrain sweeps"):

- One walking reference (flat ground; by default a held-out one near the paper's ~1 m/s and
  ~0.2 m clearance) is turned about the vertical through its start by the trial's yaw: positions,
  orientations, world-frame velocities and contact wrenches rotate, body-frame quantities do not.
  The actor observes nothing that depends on the yaw, so a trial differs only in how the robot
  meets the terrain: it approaches the first stair edge or the slope's foot at that angle.
- The terrain rises along +x from `start` (1 m ahead of the start position) and spans the whole
  path: stairs of `n_steps` steps of `step_length` treads, then a landing to the end of the path
  (plus 3 m); a slope of `slope_length`, then a level top. Behind and beside them is flat ground.
- The yaws are drawn once (seeded) and reused for every setting, so settings differ only in the
  terrain (paired trials).
- A trial runs the whole reference with the task's height terminations off (on stairs the flat
  reference's base height is meaningless); the orientation threshold stays on and stops a trial
  whose base turned or tilted that far from the (rotated) reference's. It is judged on the true
  state: it **fell** if it was stopped, or its base came closer than `min_height` to the ground
  below it, or tilted more than `max_tilt`; it
  **succeeds** if it did not fall and its final base position covers at least (1 - `tolerance`) of
  the reference's distance along the reference's (rotated) direction.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from opt2skill.data.record import Trajectory
from opt2skill.envs import evaluation_config
from opt2skill.envs.config import TerminationConfig
from opt2skill.errors import ConfigError
from opt2skill.eval.rollout import Rollout, rollout
from opt2skill.geometry import quat_mul, tilt_angle
from opt2skill.scene.terrain import Slope, Stairs, Terrain

MIN_TRAVEL_ON_TERRAIN = 0.5  # m a reference must go beyond the terrain's start for a sweep to mean something
TERRAINS = {  # name -> (unit shown, default step, default maximum)
    "stairs": ("cm", 0.02, 0.16),  # step heights in m (shown in cm), the paper's 0-16 cm
    "slope": ("deg", 2.5, 20.0),  # angles in degrees, the paper's 0-20 degrees
}


@dataclass(frozen=True)
class SweepSettings:
    terrain: str = "stairs"
    values: tuple[float, ...] = ()  # step heights (m) or angles (deg); default: 0 to max by step
    trials: int = 10
    yaw_range: float = 25.0  # degrees: initial yaw uniform in [-yaw_range, yaw_range]
    start: float = 1.0  # m from the start position to the first stair edge / the slope's foot, along +x
    step_length: float = 0.3  # m, stair tread
    n_steps: int = 10  # stairs before the landing
    slope_length: float = 6.0  # m of incline before the level top
    tolerance: float = 0.1  # share of the reference distance the robot may fall short by
    max_tilt: float = 1.0  # rad: tilted more than this counts as a fall
    seed: int = 0

    def grid(self) -> np.ndarray:
        return np.asarray(self.values, dtype=float)

    def check(self) -> None:
        if self.terrain not in TERRAINS:
            raise ConfigError(f"--terrain must be one of {', '.join(TERRAINS)}, got '{self.terrain}'")
        if not self.values:
            raise ConfigError("a sweep needs at least one terrain setting")
        if not 1 <= self.trials <= 1000:
            raise ConfigError(f"--trials must be in [1, 1000], got {self.trials}")
        if not 0 <= self.yaw_range <= 90:
            raise ConfigError(f"--yaw-range must be in [0, 90] degrees, got {self.yaw_range}")
        if not 0 <= self.tolerance < 1:
            raise ConfigError(f"--tolerance must be in [0, 1), got {self.tolerance}")
        if not 0.3 <= self.start <= 20:
            raise ConfigError(f"--start must be in [0.3, 20] m (the robot's feet must start on flat ground), got {self.start}")
        for v in self.values:
            self.terrain_for(v, 10.0)  # the terrain's own checks name a bad value

    def terrain_for(self, value: float, distance: float, x0: float = 0.0) -> Terrain:
        """The terrain of one setting for a path of `distance` m starting at x = x0: it begins
        `start` m ahead and is long and wide enough for the path at any of the trials' yaws."""
        begin = x0 + self.start
        landing = max(6.0, x0 + distance + 3.0 - begin)
        width = max(20.0, 2 * (distance * np.sin(np.radians(self.yaw_range)) + 3.0))
        if self.terrain == "stairs":
            landing = max(self.step_length, landing - (self.n_steps - 1) * self.step_length)
            return Stairs(float(value), self.step_length, begin, self.n_steps, width=width, landing=landing)
        return Slope(float(value), begin, self.slope_length, width=width, landing=max(0.0, landing - self.slope_length))


def default_values(terrain: str, step: float | None = None, maximum: float | None = None) -> tuple[float, ...]:
    if terrain not in TERRAINS:
        raise ConfigError(f"--terrain must be one of {', '.join(TERRAINS)}, got '{terrain}'")
    _, default_step, default_max = TERRAINS[terrain]
    step, maximum = step or default_step, default_max if maximum is None else maximum
    if step <= 0 or maximum < 0:
        raise ConfigError(f"--step must be > 0 and --max >= 0, got {step} and {maximum}")
    return tuple(float(v) for v in np.round(np.arange(0.0, maximum + step / 2, step), 6))


def rotate_about_z(traj: Trajectory, yaw: float) -> Trajectory:
    """The same motion turned by `yaw` about the vertical through its first base position."""
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    pivot = np.array([*traj.qpos[0, :2], 0.0])

    def point(p):
        return (p - pivot) @ rot.T + pivot

    qpos, qvel = traj.qpos.copy(), traj.qvel.copy()
    qpos[:, :3] = point(traj.qpos[:, :3])
    qpos[:, 3:7] = quat_mul(np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]), traj.qpos[:, 3:7])
    qvel[:, :3] = traj.qvel[:, :3] @ rot.T  # world frame; the angular velocity is in the body frame
    wrench = traj.contact_wrench.copy()
    wrench[..., :3] = traj.contact_wrench[..., :3] @ rot.T
    wrench[..., 3:] = traj.contact_wrench[..., 3:] @ rot.T
    return replace(traj, qpos=qpos, qvel=qvel, contact_wrench=wrench, ee_pos=point(traj.ee_pos), com=point(traj.com))


@dataclass
class Trial:
    yaw: float  # rad
    fell: bool
    fall_time: float | None  # s
    progress: float  # m covered along the reference's direction
    distance: float  # m, the reference's
    success: bool


def judge(reference: Trajectory, tracked: Trajectory, terrain: Terrain, z_offset: float, yaw: float,
          min_height: float, max_tilt: float, tolerance: float, stopped: bool = False) -> Trial:
    """Did the robot cover the (rotated) reference's distance without falling? On the true state.
    `stopped`: the rollout ended before the reference did (lost orientation, diverged physics)."""
    base = tracked.qpos[:, :3].copy()
    base[:, 2] += z_offset  # tracked heights are from the start level
    clearance = base[:, 2] - terrain.height(base[:, :2])
    fallen = (clearance < min_height) | (tilt_angle(tracked.qpos[:, 3:7]) > max_tilt)
    first = int(np.argmax(fallen)) if fallen.any() else None
    path = reference.qpos[-1, :2] - reference.qpos[0, :2]
    distance = float(np.linalg.norm(path))
    progress = float((tracked.qpos[-1, :2] - reference.qpos[0, :2]) @ (path / distance)) if distance > 0.05 else 0.0
    fell = first is not None or stopped
    fall_time = float(tracked.time[first]) if first is not None else (float(tracked.time[-1]) if stopped else None)
    covered = distance <= 0.05 or progress >= (1 - tolerance) * distance
    return Trial(yaw, fell, fall_time, progress, distance,
                 bool(not fell and covered and tracked.num_frames == reference.num_frames))


@dataclass
class SweepResult:
    settings: SweepSettings
    policy: dict[str, Any]
    reference: dict[str, Any]  # dataset, index, params, distance
    trials: dict[float, list[Trial]] = field(default_factory=dict)
    terrains: dict[float, Terrain] = field(default_factory=dict)
    elapsed: float = 0.0

    def rates(self) -> np.ndarray:
        return np.array([np.mean([t.success for t in self.trials[v]]) for v in self.settings.values])

    def shown(self, value: float) -> str:
        unit = TERRAINS[self.settings.terrain][0]
        return f"{100 * value:g} cm" if unit == "cm" else f"{value:g} deg"

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": "opt2skill-sweep", "format_version": 1, "settings": dataclasses.asdict(self.settings),
            "policy": self.policy, "reference": self.reference, "elapsed_s": self.elapsed,
            "success_rate": {self.shown(v): r for v, r in zip(self.settings.values, self.rates())},
            "trials": {self.shown(v): [dataclasses.asdict(t) for t in ts] for v, ts in self.trials.items()},
        }

    def rows(self) -> list[list[str]]:
        rows = []
        for v, rate in zip(self.settings.values, self.rates()):
            ts = self.trials[v]
            fell = sum(t.fell for t in ts)
            progress = np.mean([t.progress / t.distance if t.distance > 0.05 else 1.0 for t in ts])
            rows.append([self.shown(v), f"{rate:.0%} ({sum(t.success for t in ts)}/{len(ts)})", str(fell),
                         f"{progress:.0%}"])
        return rows

    def markdown(self) -> str:
        s = self.settings
        head = ["step height" if s.terrain == "stairs" else "slope angle", "success", "falls", "mean progress"]
        lines = [f"# Terrain sweep ({s.terrain}): {self.policy.get('name', '')}", "",
                 f"- reference: {self.reference['description']}",
                 f"- {s.trials} trials per setting, initial yaw uniform in [-{s.yaw_range:g}, {s.yaw_range:g}] deg "
                 f"(seed {s.seed}, the same yaws for every setting); terrain starts {s.start:g} m ahead along +x",
                 f"- success: no fall (base within {self.reference['min_height']:g} m of the ground or tilted more "
                 f"than {s.max_tilt:g} rad) and at least {1 - s.tolerance:.0%} of the reference distance covered", "",
                 "| " + " | ".join(head) + " |", "|" + "|".join(" --- " for _ in head) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in self.rows()]
        return "\n".join(lines) + "\n"


def choose_reference(dataset, training: list[str] | None, index: int | None) -> tuple[int, str]:
    """Dataset position of the sweep's reference and what it is to the policy (held out, trained
    on, unknown): the given generation index, else the held-out reference (a training one when
    none is held out, and the note says so) closest to the paper's set-up, speed ~1 m/s and
    clearance ~0.2 m (when the references have those parameters)."""
    from opt2skill.eval.references import dataset_fingerprints, position_fingerprint

    trained = set(training) if training is not None else None

    def relation(p: int) -> str:
        if trained is None:
            return "unknown whether the policy trained on it (its training dataset is gone or changed)"
        return "used in training, NOT held out" if position_fingerprint(dataset, p) in trained else "held out"

    if index is not None:
        position = dataset.position(index)
        return position, relation(position)
    prints = dataset_fingerprints(dataset)
    held_out = [p for p in range(len(dataset)) if trained is not None and prints[p] not in trained]
    candidates = held_out or list(range(len(dataset)))

    def distance_to_paper(p: int) -> float:
        params = dataset.meta(p).params
        return abs(params.get("speed", 1.0) - 1.0) + abs(params.get("clearance", 0.2) - 0.2)

    position = min(candidates, key=distance_to_paper)
    note = relation(position)
    if trained is not None and not held_out:
        note += f": {dataset.root} has no held-out reference (pass one with --dataset)"
    return position, note


def base_travel(traj: Trajectory) -> float:
    """m the reference's base moves over the ground, start to end."""
    return float(np.linalg.norm(traj.qpos[-1, :2] - traj.qpos[0, :2]))


def check_reaches_terrain(reference: Trajectory, settings: SweepSettings, description: str) -> None:
    """A sweep measures walking onto terrain: a reference that never gets there (a squat, a motion
    in place) would report success for terrain the robot never met. Decided from the motion itself."""
    travel, needed = base_travel(reference), settings.start + MIN_TRAVEL_ON_TERRAIN
    if travel < needed:
        raise ConfigError(f"the sweep's reference {description} moves its base {travel:.2f} m; the terrain starts "
                          f"{settings.start:g} m ahead, so a sweep needs a reference that walks at least {needed:g} m: "
                          "this run's task does not walk far enough to be swept")


def sweep_yaws(settings: SweepSettings) -> np.ndarray:
    rng = np.random.default_rng(settings.seed)
    return np.radians(rng.uniform(-settings.yaw_range, settings.yaw_range, settings.trials))


def run_sweep(run_policy, reference: Trajectory, reference_info: dict[str, Any], settings: SweepSettings,
              threads: int | None = None, progress: bool = True) -> tuple[SweepResult, dict[float, list[Rollout]]]:
    """Every setting's trials with the run's policy (`eval.evaluate.RunPolicy`)."""
    settings.check()
    check_reaches_terrain(reference, settings, reference_info.get("description", ""))
    from tqdm import tqdm

    tracking = run_policy.spec.tracking
    # On stairs and slopes the flat reference's base height means nothing: only the orientation
    # threshold stays on, to stop a trial that has lost the reference (the judge then calls it a fall).
    keep = tracking.terminations.max_orientation_error
    config = dataclasses.replace(evaluation_config(tracking), terminations=TerminationConfig(
        max_height_error=0.0, max_orientation_error=keep, max_xy_error=0.0, min_height=0.0))
    min_height = tracking.terminations.min_height or 0.4
    yaws = sweep_yaws(settings)
    turned = [rotate_about_z(reference, float(y)) for y in yaws]
    distance = base_travel(reference)
    info = {**reference_info, "distance": distance, "min_height": min_height}
    result = SweepResult(settings, run_policy.info, info)
    rollouts: dict[float, list[Rollout]] = {}
    start = time.perf_counter()
    total = len(settings.values) * settings.trials * (reference.num_frames - 1)
    with tqdm(total=total, disable=not progress, unit="step", unit_scale=True, desc=f"{settings.terrain} sweep",
              dynamic_ncols=True, leave=False) as bar:
        for value in settings.values:
            terrain = result.terrains[value] = settings.terrain_for(value, distance, float(reference.qpos[0, 0]))
            rs = rollout(run_policy.robot, turned, run_policy.policy, config, seed=settings.seed, terrain=terrain,
                         threads=threads, progress=bar.update)
            rollouts[value] = rs
            result.trials[value] = [judge(r.reference, r.tracked, terrain, r.z_offset, float(y), min_height,
                                          settings.max_tilt, settings.tolerance, stopped=r.fell)
                                    for r, y in zip(rs, yaws)]
    result.elapsed = time.perf_counter() - start
    return result, rollouts


def sweep_reference(dataset, run_policy, run, index: int | None = None) -> tuple[Trajectory, dict[str, Any]]:
    """The sweep's reference from `dataset` (`choose_reference`) for the policy of `run`, checked
    against the policy's task and contacts, and its description for the outputs."""
    from pathlib import Path

    from opt2skill.eval.evaluate import training_fingerprints
    from opt2skill.eval.references import check_metric_fields

    position, relation = choose_reference(dataset, training_fingerprints(run_policy.spec, run), index)
    check_metric_fields(dataset, run_policy.spec.tracking.task, position, run_policy.spec.contact_names(run_policy.robot))
    reference = dataset[position]
    params = ", ".join(f"{k}={v:.3g}" for k, v in reference.params.items() if isinstance(v, (int, float)))
    root = Path(dataset.root).resolve()
    index = int(dataset.indices[position])
    info = {"dataset": str(root), "index": index, "params": reference.params,
            "description": f"#{index} of {root} ({params}), {reference.duration:.1f} s, {relation}"}
    return reference, info


def write_sweep(result: SweepResult, out, label: str) -> list:
    """OUT/sweep.json, sweep.md and sweep.png (success against the setting), each written whole."""
    from pathlib import Path

    from opt2skill.data.atomic import write_report_files
    from opt2skill.eval.plots import plot_success

    s = result.settings
    json_path, md_path = write_report_files(out, "sweep", result.to_dict(), result.markdown())
    xs = np.array(s.values) * (100 if s.terrain == "stairs" else 1)
    plot = plot_success(xs, result.rates(), Path(out) / "sweep.png", "step height (cm)" if s.terrain == "stairs" else "slope (deg)",
                        f"{s.terrain}: {s.trials} trials per setting", label=label)
    return [json_path, md_path, plot]
