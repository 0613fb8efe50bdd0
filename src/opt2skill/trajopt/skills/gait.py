"""Walking plan: contact timeline, centre-of-mass path, footholds and swing-foot references.

Pure geometry and timing (no optimization): the walking task turns a `GaitPlan` into phases.

- Timeline: stand, then `n` steps of (double support, single support), then stand until the end.
  The first swing foot is the one on the side the robot turns or moves towards (left otherwise).
- Commanded velocity (forward, lateral in the heading frame, yaw rate) follows smooth ramps: up
  after the first step starts, down so that it is zero when the last two footholds are placed.
- Footholds: each foot lands where the CoM path will be at the middle of that stance, offset by the
  stand pose's foot offset in the heading frame; its yaw is the heading there. So the last two
  steps bring the feet side by side, and stepping in place (speed 0) lands on the same spots.
- A task may move each foothold (`place`: stairs put every foot on a tread, clear of the nosings,
  at the tread's height); the support height is the mean of the two feet's ground heights, each
  foot's moving smoothly from its lift-off to its touchdown height (the base follows it on stairs).
- Swing references are cubic splines. `swing_reference` (level ground): horizontal position and yaw
  move with 3s^2 - 2s^3; height rises with the same cubic to the clearance at mid-swing and comes down
  symmetrically, with zero velocity at lift-off, apex and touchdown. `stair_swing_reference`: the
  foot first rises to the clearance above the higher foothold, then moves across, then lowers, so
  that the toe and heel pass over the nosings between.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from opt2skill.data.record import FRAME_DT


def on_frame_grid(seconds: float) -> float:
    """A duration rounded to the 200 Hz frame grid (phase switches fall on frames)."""
    return max(1, int(round(seconds / FRAME_DT))) * FRAME_DT


def smoothstep(s: np.ndarray | float) -> np.ndarray | float:
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def yaw_matrix(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Foothold:
    foot: str
    position: np.ndarray  # (3,) sole-centre position, world
    yaw: float


@dataclass(frozen=True)
class Step:
    """One step: double support from `start`, then `swing` foot in the air until `touchdown`."""

    start: float
    liftoff: float
    touchdown: float
    swing: str
    stance: str
    origin: Foothold  # where the swing foot leaves
    target: Foothold  # where it lands


@dataclass(frozen=True)
class GaitSpec:
    speed: float  # forward, m/s (heading frame)
    lateral_speed: float
    yaw_rate: float
    clearance: float  # m, swing-foot apex above the ground
    step_duration: float  # s, one step = double support + single support
    double_support: float  # fraction of a step in double support
    stand_start: float  # s
    duration: float  # s, whole motion
    stand_end_min: float  # s, the last standing phase lasts at least this long
    ramp: float  # s, time to reach (and leave) the commanded velocity
    steps: int = 0  # 0: as many as fit in `duration`


@dataclass
class GaitPlan:
    steps: list[Step]
    times: np.ndarray  # 200 Hz grid over the motion
    com_xy: np.ndarray  # (T, 2) planned CoM path
    heading: np.ndarray  # (T,) planned heading (yaw)
    velocity: np.ndarray  # (T, 3) commanded world velocity: vx, vy, yaw rate
    duration: float
    stand_start: float
    walk_end: float  # touchdown of the last step
    support_z: np.ndarray | None = None  # (T,) mean ground height under the two feet (None: level)

    def sample(self, t: float) -> tuple[np.ndarray, float, np.ndarray]:
        """CoM xy, heading and world velocity (vx, vy, wz) at time t."""
        i = min(int(round(t / FRAME_DT)), len(self.times) - 1)
        return self.com_xy[i], float(self.heading[i]), self.velocity[i]

    def support_height(self, t: float) -> float:
        """Support height at time t relative to the start (0 on level ground)."""
        if self.support_z is None:
            return 0.0
        i = min(int(round(t / FRAME_DT)), len(self.times) - 1)
        return float(self.support_z[i] - self.support_z[0])


# (foot, nominal sole-centre position (3,), yaw) -> the foothold's sole-centre position (3,)
PlaceFoot = Callable[[str, np.ndarray, float], np.ndarray]


def plan_gait(spec: GaitSpec, feet: dict[str, Foothold], com_xy0: np.ndarray, place: PlaceFoot | None = None) -> GaitPlan:
    """The plan for `spec`, starting from the stand footholds `feet` (two feet, left first);
    `place` moves each planned foothold (default: where the CoM path puts it, at its start height)."""
    step = on_frame_grid(spec.step_duration)
    ds = on_frame_grid(spec.double_support * step) if spec.double_support > 0 else 0.0
    ss = on_frame_grid(step - ds)
    step = ds + ss
    t0 = on_frame_grid(spec.stand_start)
    n = spec.steps or int((spec.duration - t0 - spec.stand_end_min) // step)
    n = max(n, 2)
    walk_end = t0 + n * step
    duration = max(on_frame_grid(spec.duration), on_frame_grid(walk_end + spec.stand_end_min))

    times = np.arange(int(round(duration / FRAME_DT)) + 1) * FRAME_DT
    # Velocity envelope: 0 -> 1 from the first lift-off, 1 -> 0 by the second-to-last touchdown.
    up_start = t0 + ds
    down_end = max(walk_end - step, up_start)
    ramp = min(spec.ramp, 0.5 * (down_end - up_start))
    if ramp > 0:
        envelope = smoothstep((times - up_start) / ramp) * smoothstep((down_end - times) / ramp)
    else:
        envelope = np.zeros_like(times)
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (envelope[1:] + envelope[:-1]) * spec.yaw_rate * FRAME_DT)])
    local = np.array([spec.speed, spec.lateral_speed])
    world_v = envelope[:, None] * np.stack(
        [np.cos(heading) * local[0] - np.sin(heading) * local[1], np.sin(heading) * local[0] + np.cos(heading) * local[1]], 1
    )
    com_xy = com_xy0 + np.concatenate([np.zeros((1, 2)), np.cumsum(0.5 * (world_v[1:] + world_v[:-1]) * FRAME_DT, 0)])
    velocity = np.column_stack([world_v, envelope * spec.yaw_rate])

    def at(t: float) -> int:
        return min(int(round(t / FRAME_DT)), len(times) - 1)

    offsets = {name: f.position[:2] - com_xy0 for name, f in feet.items()}  # heading 0 at the start

    left, right = feet  # the robot's feet, left first
    first = right if (spec.lateral_speed < 0 or (spec.lateral_speed == 0 and spec.yaw_rate < 0)) else left
    other = {left: right, right: left}
    current = dict(feet)
    steps: list[Step] = []
    swing = first
    for i in range(n):
        start = t0 + i * step
        liftoff, touchdown = start + ds, start + step
        # The foot lifts again two steps later, or never (then the stance lasts to the end).
        next_liftoff = touchdown + step + ds if i + 2 < n else duration
        mid = at(0.5 * (touchdown + next_liftoff))
        yaw = float(heading[mid])
        xy = com_xy[mid] + yaw_matrix(yaw)[:2, :2] @ offsets[swing]
        position = np.array([xy[0], xy[1], feet[swing].position[2]])
        if place is not None:
            position = np.asarray(place(swing, position, yaw), dtype=float)
        target = Foothold(swing, position, yaw)
        steps.append(Step(start, liftoff, touchdown, swing, other[swing], current[swing], target))
        current[swing] = target
        swing = other[swing]
    support_z = None
    if any(abs(st.target.position[2] - st.origin.position[2]) > 1e-9 for st in steps):
        support_z = _support_heights(times, steps, feet)
    return GaitPlan(
        steps=steps,
        times=times,
        com_xy=com_xy,
        heading=heading,
        velocity=velocity,
        duration=duration,
        stand_start=t0,
        walk_end=walk_end,
        support_z=support_z,
    )


def _support_heights(times: np.ndarray, steps: list[Step], feet: dict[str, Foothold]) -> np.ndarray:
    """Mean of the two feet's heights, each moving with a smoothstep over its swing."""
    heights = {name: np.full(len(times), f.position[2]) for name, f in feet.items()}
    for step in steps:
        s = (times - step.liftoff) / (step.touchdown - step.liftoff)
        z = step.origin.position[2] + (step.target.position[2] - step.origin.position[2]) * smoothstep(s)
        after = times >= step.liftoff
        heights[step.swing][after] = z[after]
    return np.mean(list(heights.values()), axis=0)


def swing_reference(step: Step, t: float, clearance: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Swing-foot position, yaw and linear velocity at time t within the step's single support."""
    span = step.touchdown - step.liftoff
    s = float(np.clip((t - step.liftoff) / span, 0.0, 1.0))
    h = smoothstep(s)
    dh = 6.0 * s * (1.0 - s) / span
    a, b = step.origin, step.target
    position = a.position + (b.position - a.position) * h
    velocity = (b.position - a.position) * dh
    yaw = a.yaw + _wrap(b.yaw - a.yaw) * h
    half = 2.0 * s if s <= 0.5 else 2.0 - 2.0 * s
    position = position.copy()
    position[2] += clearance * smoothstep(half)
    velocity = velocity.copy()
    velocity[2] += clearance * 6.0 * half * (1.0 - half) * (2.0 if s <= 0.5 else -2.0) / span
    return position, yaw, velocity


def stair_swing_reference(step: Step, t: float, clearance: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Swing-foot position, yaw and linear velocity for a step between levels: up to `clearance`
    above the higher foothold (first 35 % of the swing), across (15 to 85 %), down (last 35 %)."""
    span = step.touchdown - step.liftoff
    s = float(np.clip((t - step.liftoff) / span, 0.0, 1.0))
    a, b = step.origin, step.target
    top = max(a.position[2], b.position[2]) + clearance
    across, d_across = _ramp(s, 0.15, 0.85)
    up, d_up = _ramp(s, 0.0, 0.35)
    down, d_down = _ramp(s, 0.65, 1.0)
    position = a.position + (b.position - a.position) * across
    velocity = (b.position - a.position) * d_across / span
    position[2] = a.position[2] + (top - a.position[2]) * up - (top - b.position[2]) * down
    velocity[2] = ((top - a.position[2]) * d_up - (top - b.position[2]) * d_down) / span
    yaw = a.yaw + _wrap(b.yaw - a.yaw) * across
    return position, yaw, velocity


def _ramp(s: float, s0: float, s1: float) -> tuple[float, float]:
    """smoothstep from 0 at s0 to 1 at s1, and its derivative with respect to s."""
    u = float(np.clip((s - s0) / (s1 - s0), 0.0, 1.0))
    return u * u * (3.0 - 2.0 * u), 6.0 * u * (1.0 - u) / (s1 - s0)


def _wrap(angle: float) -> float:
    return float((angle + np.pi) % (2 * np.pi) - np.pi)
