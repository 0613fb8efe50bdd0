"""The feedback expert acting in a tracking environment: actions for every world from the privileged state.

At policy step t a world tracks its reference at frame t's instant. The expert reads the world's
simulated state (not the actor's noisy observations), evaluates the feedback law of its reference
(`FeedbackExpert`) and returns the action whose PD targets make the world's servos apply that torque
(with the world's own, randomized gains), by default with their own PD tracking the reference on
top (`ExpertConfig.servo`): `pd_targets`, then the environment's action map. Everything is
batched over the worlds; there is no loop over worlds.

The law is local: far from its reference it is not a controller any more. `ExpertConfig` says how far
a state may be from the reference for the expert's action to count as a label, and how the torque
becomes a held PD target (docs/distill.md has the measured figures behind the defaults).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.envs import TrackingEnv
from opt2skill.envs.measure import Readings
from opt2skill.errors import ConfigError, DataError
from opt2skill.expert.feedback import FeedbackExpert, pd_targets
from opt2skill.expert.standing import StandingLQR
from opt2skill.geometry import quat_mul, quat_to_mat


SERVO_FORMS = ("reference", "state")


@dataclass(frozen=True)
class ExpertConfig:
    """How the law becomes PD targets, and how far from its reference it is trusted (0: no limit).

    `standing_gains`: standing segments get stabilizing gains of their own (`expert.standing`).
    `servo`: how the law's torque u becomes a PD target held for the policy step.
    "reference" (the default): the target q_ref + (u + kd qd_ref) / kp, at the reference
    `reference_ahead` policy steps ahead (the middle of the step the target is held over), so the
    servo applies u + kp (q_ref - q) + kd (qd_ref - qd): its own PD, which runs at the physics rate,
    tracks the reference on top of the law, as in the validation's feedback replay
    (`data.replay`). "state": the target at which the servo produces u alone at the measured state,
    computed at the joint positions predicted `lead` policy steps ahead (q + lead h qd), since the
    torque drifts by kp qd over the step; the law alone then holds the robot at 200 Hz, which
    loses heavy boxes and some walks (docs/expert.md, "The servo's PD around the reference").
    `joint_losses`: the motors also supply the simulated joints' damping and friction loss, which
    the optimizer's rigid-body model leaves out. docs/distill.md has the measurements behind the
    defaults.
    """

    # What the law reads. "state": the simulator's true state (the teacher of asymmetric DAgger).
    # "observations": the joint positions and velocities, base velocities and tilt the actor was given
    # with its latest observation, noise included: a perfect student with the actor's inputs, which
    # measures what observation noise does to the law itself (benchmarks/expert_noise.py). Validity is
    # always judged on the true state. The two are the same without observation noise.
    reads: str = "state"
    servo: str = "reference"  # "reference" | "state", see above
    reference_ahead: float = 0.5  # policy steps ("reference" servo)
    lead: float = 0.75  # policy steps ("state" servo)
    joint_losses: bool = True
    standing_gains: bool = True  # LQR gains of their own in standing segments (expert.standing)
    friction_smoothing: float = 0.05  # rad/s, friction loss as f tanh(qd / smoothing)
    max_base_position: float = 0.15  # m, base translation error
    max_base_rotation: float = 0.3  # rad, base rotation error
    max_joint: float = 0.5  # rad, largest joint-position error

    def check(self) -> None:
        if self.reads not in ("observations", "state"):
            raise ConfigError(f"expert reads must be 'observations' or 'state', got '{self.reads}'")
        if self.servo not in SERVO_FORMS:
            raise ConfigError(f"expert servo must be one of {', '.join(SERVO_FORMS)}, got '{self.servo}'")
        if not 0 <= self.lead <= 5:
            raise ConfigError(f"expert lead must be in [0, 5] policy steps, got {self.lead}")
        if not 0 <= self.reference_ahead <= 5:
            raise ConfigError(f"expert reference_ahead must be in [0, 5] policy steps, got {self.reference_ahead}")
        if self.friction_smoothing <= 0:
            raise ConfigError(f"expert friction_smoothing must be > 0 rad/s, got {self.friction_smoothing}")
        for name in ("max_base_position", "max_base_rotation", "max_joint"):
            if getattr(self, name) < 0:
                raise ConfigError(f"expert limit '{name}' must be >= 0 (0: no limit), got {getattr(self, name)}")

    def valid(self, deviation: np.ndarray, nu: int) -> np.ndarray:
        """(N,) bool: deviations (N, 2 nv) (tangent space, `FeedbackExpert.torque_and_deviation`) inside the limits."""
        ok = np.ones(len(deviation), dtype=bool)
        for limit, block in ((self.max_base_position, deviation[:, 0:3]), (self.max_base_rotation, deviation[:, 3:6])):
            if limit:
                ok &= np.einsum("ij,ij->i", block, block) <= limit * limit
        if self.max_joint:
            ok &= np.abs(deviation[:, 6:6 + nu]).max(axis=1) <= self.max_joint
        return ok


def as_read(qpos: np.ndarray, qvel: np.ndarray, readings: Readings) -> tuple[np.ndarray, np.ndarray]:
    """The state (MuJoCo layout) as the readings have it: their joint positions and velocities, base
    velocities, and the base tilted so that its projected gravity points along the read one; the base
    position and heading (which the actor does not read) stay true."""
    qpos, qvel = qpos.copy(), qvel.copy()
    nu = readings.joint_pos.shape[1]
    qpos[:, 7:7 + nu] = readings.joint_pos
    qvel[:, 6:6 + nu] = readings.joint_vel
    quat = qpos[:, 3:7]
    true_g = -quat_to_mat(quat)[:, 2, :]  # R^T (0, 0, -1), R: body -> world
    read_g = readings.gravity / np.linalg.norm(readings.gravity, axis=1, keepdims=True)
    # R' = R Q with Q^T true_g = read_g: Q turns read_g onto true_g (about read_g x true_g)
    axis = np.cross(read_g, true_g)
    sin = np.linalg.norm(axis, axis=1, keepdims=True)
    cos = np.einsum("ij,ij->i", read_g, true_g)[:, None]
    half = 0.5 * np.arctan2(sin, cos)
    turn = np.concatenate([np.cos(half), np.sin(half) * axis / np.maximum(sin, 1e-12)], axis=1)
    qpos[:, 3:7] = quat_mul(quat, turn)
    # the base velocities in the read (tilted) body frame; MuJoCo's free joint has the linear one in world axes
    qvel[:, 0:3] = np.einsum("nij,nj->ni", quat_to_mat(qpos[:, 3:7]), readings.base_lin_vel)
    qvel[:, 3:6] = readings.base_ang_vel
    return qpos, qvel


class EnvExpert:
    """The feedback law of each world's reference, as actions of `env`."""

    def __init__(self, env: TrackingEnv, trajectories: list[Trajectory], config: ExpertConfig | None = None):
        """`trajectories`: the records of the env's reference bank, in the bank's order (with gains)."""
        if len(trajectories) != env.bank.num_trajectories:
            raise DataError(f"the expert needs the {env.bank.num_trajectories} trajectories of the environment's "
                            f"references in order, got {len(trajectories)}")
        lengths = np.array([t.num_frames for t in trajectories])
        if np.any(lengths != env.bank.length):
            raise DataError("the expert's trajectories are not the environment's references (frame counts differ)")
        self.env = env
        self.config = config or ExpertConfig()
        self.config.check()
        self.expert = FeedbackExpert(env.robot, trajectories, StandingLQR() if self.config.standing_gains else None)
        model = env.robot.mj_model
        self._damping, self._friction = model.dof_damping[6:].copy(), model.dof_frictionloss[6:].copy()

    def act(self) -> tuple[np.ndarray, np.ndarray]:
        """(actions (N, nu), valid (N,) bool) for the current state of every world (as read, see
        `ExpertConfig.reads`, from the latest `env.observations()`)."""
        env, cfg = self.env, self.config
        state = env.state
        qpos = state.qpos.copy()
        qpos[:, 2] -= env.sim.z_offset  # references stand on z = 0; the world stands on its terrain
        time = env.frame * FRAME_DT
        torque, deviation = self.expert.torque_and_deviation(env.traj, time, qpos, state.qvel)
        q, qd = state.joint_pos, state.joint_vel
        if cfg.reads == "observations" and env.readings is not None and env.noise_factor > 0:
            seen_qpos, seen_qvel = as_read(qpos, state.qvel, env.readings)
            torque = self.expert.torque(env.traj, time, seen_qpos, seen_qvel)
            q, qd = env.readings.joint_pos, env.readings.joint_vel
        if cfg.joint_losses:
            torque = torque + self._damping * qd + self._friction * np.tanh(qd / cfg.friction_smoothing)
        kp, kd, _ = env.sim.gains()
        if cfg.servo == "reference":
            q_ref, qd_ref = self.expert.reference_joints(env.traj, time + cfg.reference_ahead * env.sim.policy_dt)
            targets = pd_targets(torque, q_ref, qd_ref, kp, kd)
        else:
            targets = pd_targets(torque, q + cfg.lead * env.sim.policy_dt * qd, qd, kp, kd)
        return env.actions_for_targets(targets), cfg.valid(deviation, env.nu)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """As a policy for `envs.evaluation.track` (the observation is ignored: the expert reads the state)."""
        return self.act()[0]
