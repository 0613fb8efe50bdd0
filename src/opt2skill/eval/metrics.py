"""The paper's tracking metrics (Section IV-B, Tables III and IV) for one tracked trajectory.

Both inputs are trajectory records on the same 200 Hz frames: the reference, and what the robot
did (the same fields, built from the simulated states). A rollout that ended early (a fall) is
compared on the frames it has. Definitions are in docs/eval.md; in short:

- per-frame errors are means over the compared frames (and over joints or end effectors);
- end-effector errors are in the base (torso) frame: "local task-space accuracy";
- drift errors compare the final frame, in the reference's final heading frame: E_pos-x is the
  along-heading position error over the reference path length (%), E_pos-y and E_yaw are the
  lateral position and yaw errors divided by the number of frames ("per step", 200 Hz).

Beside the paper's metrics, `pace` is E_pos-x with its sign kept: the distance the robot covered
along the reference's final heading over the reference path length (1 on pace, above 1 ahead of
the reference, below 1 behind it), which tells overshooting from lagging; and `turn` is the final
yaw error with its sign (tracked minus reference, rad; positive: turned left, counter-clockwise seen
from above), which tells a policy that turns one way in every walk from one that wanders
(E_yaw = 1000 |turn| / frames); and `lead` is the final along-heading error over the time tracked
(m/s, > 0 ahead): how much faster than its reference the robot went. E_pos-x divides the same error
by the path length, so a policy a constant 0.1 m/s ahead scores 50 % on a 0.2 m/s walk and 10 % on
a 1 m/s walk; `lead` tells such an offset from a policy that is off only on slow walks, and it is
defined for walks in place too.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from opt2skill.data.record import FRAME_DT, FRAME_FIELDS, Trajectory
from opt2skill.geometry import yaw_of

# Name, unit and scale (from SI) of each metric, in the order of Table III then Table IV.
METRICS = {
    "E_joint": ("rad", 1.0),
    "E_vel_x": ("cm/s", 100.0),
    "E_vel_yaw": ("rad/s", 1.0),
    "E_ee_hand": ("cm", 100.0),
    "E_ee_foot": ("cm", 100.0),
    "E_pos_x": ("%", 100.0),
    "E_pos_y": ("mm/step", 1000.0),
    "E_yaw": ("mrad/step", 1000.0),
    "E_force": ("N", 1.0),
    "E_torque": ("N m", 1.0),
}
# Reference paths shorter than this have no meaningful "% of path length" (stepping in place).
MIN_PATH_LENGTH = 0.05  # m


@dataclass(frozen=True)
class TrackingErrors:
    """Table III and IV metrics of one rollout, in the paper's units (see METRICS)."""

    E_joint: float
    E_vel_x: float
    E_vel_yaw: float
    E_ee_hand: float
    E_ee_foot: float
    E_pos_x: float  # NaN when the reference path is shorter than MIN_PATH_LENGTH
    E_pos_y: float
    E_yaw: float
    E_force: float  # NaN when the records carry no contacts, or the reference no dynamics
    E_torque: float  # NaN when the reference has no dynamics (a kinematic record)
    frames: int  # frames compared
    fell: bool
    # 1 + the signed along-heading error over the path (E_pos-x = 100 |pace - 1|); NaN like E_pos-x
    pace: float = float("nan")
    # rad, the final yaw error with its sign (tracked - reference; > 0: turned left); E_yaw = 1000 |turn| / frames
    turn: float = float("nan")
    # m/s, the signed along-heading final error over the time tracked (> 0: ahead of the reference)
    lead: float = float("nan")

    def as_dict(self) -> dict:
        return asdict(self)


def tracking_errors(
    reference: Trajectory,
    tracked: Trajectory,
    hands: tuple[str, ...] = ("left_hand", "right_hand"),
    feet: tuple[str, ...] = ("left_foot", "right_foot"),
    fell: bool = False,
) -> TrackingErrors:
    n = tracked.num_frames
    if n < 2 or n > reference.num_frames:
        raise ValueError(f"tracked has {n} frames; need 2 to {reference.num_frames} (the reference's)")
    ref = _first_frames(reference, n)

    joint_err = np.abs(tracked.qpos[:, 7:] - ref.qpos[:, 7:]).mean()
    vel_x_err = np.abs(tracked.base_lin_vel[:, 0] - ref.base_lin_vel[:, 0]).mean()
    vel_yaw_err = np.abs(tracked.base_ang_vel[:, 2] - ref.base_ang_vel[:, 2]).mean()
    hand_err = _ee_error(ref, tracked, hands)
    foot_err = _ee_error(ref, tracked, feet)

    # Drift, in the reference's final heading frame.
    heading = yaw_of(ref.qpos[-1, 3:7])
    axis_x = np.array([np.cos(heading), np.sin(heading)])
    axis_y = np.array([-np.sin(heading), np.cos(heading)])
    final_err = tracked.qpos[-1, :2] - ref.qpos[-1, :2]
    path = np.linalg.norm(np.diff(ref.qpos[:, :2], axis=0), axis=1).sum()
    lead = final_err @ axis_x / ((n - 1) * FRAME_DT)
    ahead = final_err @ axis_x / path if path >= MIN_PATH_LENGTH else np.nan
    pos_x = abs(ahead)
    pos_y = abs(final_err @ axis_y) / n
    turn = _wrap(yaw_of(tracked.qpos[-1, 3:7]) - heading)
    yaw_err = abs(turn) / n

    # A kinematic reference (IK, human motion) has no torques or forces to compare with: its zeros
    # are placeholders, not a plan.
    force_err = torque_err = np.nan
    if reference.has_dynamics:
        if ref.contact_wrench.shape[1]:
            force_err = np.linalg.norm(tracked.contact_wrench[..., :3] - ref.contact_wrench[..., :3], axis=-1).mean()
        torque_err = np.abs(tracked.joint_torque - ref.joint_torque).mean()

    values = {
        "E_joint": joint_err, "E_vel_x": vel_x_err, "E_vel_yaw": vel_yaw_err, "E_ee_hand": hand_err,
        "E_ee_foot": foot_err, "E_pos_x": pos_x, "E_pos_y": pos_y, "E_yaw": yaw_err,
        "E_force": force_err, "E_torque": torque_err,
    }
    scaled = {name: float(value) * METRICS[name][1] for name, value in values.items()}
    return TrackingErrors(**scaled, frames=n, fell=bool(fell), pace=float(1.0 + ahead), turn=float(turn),
                          lead=float(lead))


def _ee_error(ref: Trajectory, tracked: Trajectory, names: tuple[str, ...]) -> float:
    missing = [name for name in names if name not in ref.ee_names or name not in tracked.ee_names]
    if missing:
        raise ValueError(f"end effectors {missing} are not in the records (they have {list(ref.ee_names)})")
    i_ref = [ref.ee_names.index(name) for name in names]
    i_trk = [tracked.ee_names.index(name) for name in names]
    return float(np.linalg.norm(tracked.ee_pos_base[:, i_trk] - ref.ee_pos_base[:, i_ref], axis=-1).mean())


def _first_frames(traj: Trajectory, n: int) -> Trajectory:
    """A view of the reference restricted to the frames the rollout covers."""
    return replace(traj, **{name: getattr(traj, name)[:n] for name in FRAME_FIELDS})


def _wrap(angle: float) -> float:
    return (angle + np.pi) % (2 * np.pi) - np.pi
