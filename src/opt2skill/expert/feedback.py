"""The trajectory optimizer's feedback law as a controller of the simulated robot.

For world n tracking trajectory i at time t (seconds from its start):

    u = u_ref(t) - K_k (x_ref(t) (-) x)

with K_k the Crocoddyl feedback gain of the solver node covering t (docs/data.md, knots), x the
measured state and x_ref(t) the reference state, both in Crocoddyl's layout, and (-) Crocoddyl's
state difference (`lie.state_diff`). The reference is the record's 200 Hz frames, which the optimizer
itself rolled out under this law (docs/trajopt.md); between frames the state difference is
interpolated linearly, and the feedforward torque is held (torques are held over each frame).

`pd_targets` turns a torque into the policy's action space: the PD target whose servo produces
exactly that torque at the current state (the inverse of `servo_torque`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.errors import DataError
from opt2skill.expert.lie import state_diff
from opt2skill.expert.standing import StandingLQR, standing_gain, standing_segments
from opt2skill.model.convert import qpos_mj_to_pin, qvel_mj_to_pin
from opt2skill.model.robot import Robot


class FeedbackExpert:
    """Time-varying linear feedback around each reference, for many worlds at once."""

    def __init__(self, robot: Robot, trajectories: Sequence[Trajectory], standing: StandingLQR | None = StandingLQR()):
        """`standing`: give standing segments (and the time past the end) gains of their own
        (`expert.standing`); None keeps DDP's gains everywhere."""
        if not trajectories:
            raise DataError("the expert needs at least one trajectory")
        self.nq, self.nu = robot.nq, robot.nu
        frames_x, frames_u, gains, knot_of_frame = [], [], [], []
        self.frame_offset = np.zeros(len(trajectories), dtype=np.int64)
        self.num_frames = np.zeros(len(trajectories), dtype=np.int64)
        gain_offset = 0
        feet = [foot.name for foot in robot.config.feet]
        for i, traj in enumerate(trajectories):
            if "gains" not in traj.knots:
                raise DataError(
                    f"trajectory {i} ({traj.task}, seed {traj.seed}) has no feedback gains; "
                    "regenerate the dataset with --keep-gains"
                )
            running = ~np.asarray(traj.knots["impulse"], dtype=bool)
            knot_time = np.asarray(traj.knots["time"][:-1])[running]
            # The node covering frame f: the last running node starting at or before its time.
            covering = np.searchsorted(knot_time, traj.time + 1e-9, side="right") - 1
            frame_knot = gain_offset + np.clip(covering, 0, len(knot_time) - 1)
            gains.append(np.asarray(traj.knots["gains"])[running])
            gain_offset += len(knot_time)
            segments = standing_segments(traj, standing, feet) if standing else ()
            for start, stop in segments:
                gains.append(standing_gain(robot, traj, (start + stop) // 2, standing)[None])
                frame_knot[start:stop] = gain_offset
                gain_offset += 1
            knot_of_frame.append(frame_knot)
            frames_x.append(np.concatenate([qpos_mj_to_pin(traj.qpos), qvel_mj_to_pin(traj.qpos, traj.qvel)], -1))
            frames_u.append(traj.joint_torque)
            self.frame_offset[i] = sum(len(x) for x in frames_x[:-1])
            self.num_frames[i] = traj.num_frames
        self._x = np.concatenate(frames_x)
        self._u = np.concatenate(frames_u)
        self._knot = np.concatenate(knot_of_frame)
        self._gains = np.concatenate(gains)

    def reference_joints(self, traj: np.ndarray, time: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The reference joint positions and velocities (N, nu) of worlds tracking `traj` (N,) at
        `time` (N,) seconds, interpolated between frames (the last frame past the end)."""
        rows, following, alpha = self._rows(np.asarray(traj, dtype=np.int64), time)
        x = (1 - alpha) * self._x[rows] + alpha * self._x[following]
        joints = slice(7, 7 + self.nu)
        return x[:, joints], x[:, self.nq + 6:self.nq + 6 + self.nu]

    def _rows(self, traj: np.ndarray, time: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The frame rows at or before `time`, the following rows, and the fraction (N, 1) between."""
        position = np.asarray(time, dtype=float) / FRAME_DT
        last = self.num_frames[traj] - 1
        frame = np.clip(np.floor(position + 1e-9).astype(np.int64), 0, last)
        following = np.minimum(frame + 1, last)
        alpha = np.clip(position - frame, 0.0, 1.0)[:, None]
        return self.frame_offset[traj] + frame, self.frame_offset[traj] + following, alpha

    def torque(self, traj: np.ndarray, time: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """Joint torques (N, nu) for worlds tracking trajectories `traj` (N,) at `time` (N,) seconds,
        measured states `qpos` (N, nq) and `qvel` (N, nv) in MuJoCo's layout."""
        return self.torque_and_deviation(traj, time, qpos, qvel)[0]

    def torque_and_deviation(self, traj: np.ndarray, time: np.ndarray, qpos: np.ndarray,
                             qvel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The torques (N, nu) and the deviations x (-) x_ref(t) (N, 2 nv) they feed back on (tangent
        space: base translation in the reference base frame, base rotation vector, joints, velocities)."""
        row, row_next, alpha = self._rows(np.asarray(traj, dtype=np.int64), time)
        x = np.concatenate([qpos_mj_to_pin(qpos), qvel_mj_to_pin(qpos, qvel)], -1)
        dx = (1 - alpha) * state_diff(self._x[row], x, self.nq) + alpha * state_diff(self._x[row_next], x, self.nq)
        return self._u[row] - np.einsum("nij,nj->ni", self._gains[self._knot[row]], dx), dx


def pd_targets(torque: np.ndarray, q: np.ndarray, qd: np.ndarray, kp: np.ndarray, kd: np.ndarray) -> np.ndarray:
    """The servo target q* with kp (q* - q) - kd qd = torque at this state (before clipping)."""
    return q + (torque + kd * qd) / kp


def servo_torque(target: np.ndarray, q: np.ndarray, qd: np.ndarray, kp: np.ndarray, kd: np.ndarray) -> np.ndarray:
    """The PD servo law (docs/conventions.md), before the torque limit."""
    return kp * (target - q) - kd * qd
