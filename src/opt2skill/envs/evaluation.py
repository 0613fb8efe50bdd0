"""Evaluation rollouts: chosen references tracked once from chosen start frames (0 by default),
returned as arrays.

`track` runs one world per reference (batched), with whatever config the environment has (use
`evaluation_config` for randomization and noise off), until every world's episode has ended once,
and returns each tracked motion on the reference's 200 Hz frames: frame 0 is the start state (the
reference's frame `start_frame`), frame k the state after k policy steps, torques and contact wrenches of frame k those applied
during step k (means over its physics steps; the last frame repeats them, as in the record).
`TrackedMotion.record` makes a trajectory record for `opt2skill.eval.metrics.tracking_errors`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from opt2skill.data.record import Trajectory, build_trajectory
from opt2skill.envs.env import CAUSES, TrackingEnv
from opt2skill.errors import ConfigError
from opt2skill.model.robot import Robot
from opt2skill.scene.slots import moving

Policy = Callable[[np.ndarray], np.ndarray]  # actor observations (N, actor_dim) -> actions (N, nu)


@dataclass
class TrackedMotion:
    position: int  # dataset position of the reference
    qpos: np.ndarray  # (T, nq), base height relative to the world's start level
    qvel: np.ndarray  # (T, nv)
    joint_torque: np.ndarray  # (T, nu)
    contact_wrench: np.ndarray  # (T, nc, 6) on each of the reference's contacts, world axes (a foot's torque
    #                             about its sole site, a point contact's 0)
    contact_active: np.ndarray  # (T, nc) bool
    reward: float  # sum of the step rewards
    terms: dict[str, float]  # sum of each term over the episode
    cause: str  # why the episode ended (CAUSES)
    reference_frames: int  # frames of the reference
    start_frame: int = 0  # the reference frame the episode started from (frame 0 of this motion)
    # (T, nmoving, 7) the moving props' poses (the bank's slots: boxes, then doors' hinge frames),
    # height relative to the start level
    prop_pose: np.ndarray | None = None
    free_slots: int = 0  # the bank's box slots (its door slots follow)

    @property
    def steps(self) -> int:
        return len(self.qpos) - 1

    @property
    def fell(self) -> bool:
        return self.cause != "time_out"

    def record(self, robot: Robot, reference: Trajectory) -> Trajectory:
        """A trajectory record of the tracked motion (the reference's names, parameters and scene; its
        moving props' poses as they moved)."""
        props = moving(reference.scene.props)  # the bank's slots: boxes, then doors
        boxes = sum(p.free for p in props)
        slots = [k if p.free else self.free_slots + k - boxes for k, p in enumerate(props)]
        poses = {} if self.prop_pose is None else {p.name: self.prop_pose[:, s] for p, s in zip(props, slots)}
        return build_trajectory(
            robot, self.qpos, self.qvel, self.joint_torque, self.contact_wrench, self.contact_active,
            task=reference.task, contact_names=reference.contact_names, params=reference.params,
            seed=reference.seed, ee_names=reference.ee_names, scene=reference.scene, prop_poses=poses,
        )


def track(env: TrackingEnv, policy: Policy, trajectories: np.ndarray,
          frames: np.ndarray | None = None) -> list[TrackedMotion]:
    """Track the references `trajectories` (indices into the env's bank), one world each, from the
    start `frames` (default 0). The environment must have as many worlds as references."""
    trajectories = np.asarray(trajectories, dtype=np.int64)
    n = env.num_envs
    if len(trajectories) != n:
        raise ConfigError(f"track needs one world per reference: {len(trajectories)} references, {n} worlds")
    frames = np.zeros(n, dtype=np.int64) if frames is None else np.asarray(frames, dtype=np.int64)
    worlds = np.arange(n)
    env.reset_worlds(worlds, trajectories, frames)
    z0 = env.sim.z_offset
    start = env.state.rows(worlds)
    qpos, qvel, torque, wrench, active, props = [start.qpos], [start.qvel], [], [], [], [start.prop_pose]
    steps, cause = np.zeros(n, dtype=np.int64), np.full(n, -1)
    reward, terms = np.zeros(n), {name: np.zeros(n) for name in env.config.rewards.terms()}
    while (cause < 0).any():
        running = cause < 0
        obs, _ = env.observations()
        result = env.step(policy(obs))
        out = env.state.rows(worlds)  # after the resets: put back the finished worlds' final outputs
        if result.episodes is not None:
            out.assign(result.episodes.worlds, result.episodes.final)
            ended = result.episodes.worlds[running[result.episodes.worlds]]
            cause[ended] = result.episodes.cause[running[result.episodes.worlds]]
        qpos.append(out.qpos)
        qvel.append(out.qvel)
        props.append(out.prop_pose)
        torque.append(out.torque_mean)
        w, a = env.contact_wrenches(out)
        wrench.append(w)
        active.append(a)
        steps[running] += 1
        reward[running] += result.reward[running]
        for name, value in result.terms.items():
            terms[name][running] += value[running]
    qpos, qvel, props = np.stack(qpos), np.stack(qvel), np.stack(props)
    torque, wrench, active = np.stack(torque), np.stack(wrench), np.stack(active)
    motions = []
    for w in range(n):
        k = steps[w]
        q = qpos[: k + 1, w].copy()
        q[:, 2] -= z0[w]
        prop = props[: k + 1, w].copy()
        prop[..., 2] -= z0[w]
        # step k's torques and wrenches belong to frame k; the last frame repeats them (as the record)
        last = [k - 1]
        motions.append(TrackedMotion(
            position=int(env.bank.positions[trajectories[w]]), qpos=q, qvel=qvel[: k + 1, w].copy(),
            joint_torque=np.concatenate([torque[:k, w], torque[last, w]]),
            contact_wrench=np.concatenate([wrench[:k, w], wrench[last, w]]),
            contact_active=np.concatenate([active[:k, w], active[last, w]]),
            reward=float(reward[w]), terms={name: float(v[w]) for name, v in terms.items()},
            cause=CAUSES[cause[w]], reference_frames=int(env.bank.length[trajectories[w]]),
            start_frame=int(frames[w]), prop_pose=prop, free_slots=env.sim.props.nfree,
        ))
    return motions
