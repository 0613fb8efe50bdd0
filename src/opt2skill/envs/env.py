"""The tracking environment: N worlds imitating reference trajectories, batched in numpy.

One `step(actions)` is one policy step (200 Hz) of every world: PD targets to the simulator,
rewards (Table I) and terminations against the reference, resets of finished worlds (new
reference, start frame and Table II parameters), observations (Section III-B). There is no loop
over worlds on this path. The environment sees the physics only through `BatchedSim`.
docs/envs.md is the contract: layouts, alignment, rewards, terminations, randomization, curriculum.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from opt2skill.data.record import FRAME_DT
from opt2skill.envs import randomization
from opt2skill.envs.config import TrackingConfig, check_reference_inputs
from opt2skill.envs.history import StridedHistory
from opt2skill.envs.measure import Measurement, Readings, measure
from opt2skill.envs.observations import ObservationLayout, fill, layout
from opt2skill.envs.reference import ReferenceBank
from opt2skill.envs.rewards import StepContext, penalty_values, reward_terms, task_errors
from opt2skill.envs.start_sampling import StartSampler
from opt2skill.errors import ConfigError
from opt2skill.model.robot import Robot
from opt2skill.model.sensors import SensorLayout, contact_wrenches
from opt2skill.sim import BatchedSim, Flat, SimConfig, SimStep
from opt2skill.sim.devices import make_sim

CAUSES = ("time_out", "fall", "height_error", "orientation_error", "xy_error", "unstable", "prop_error")


@dataclass
class Episodes:
    """Episodes that ended in one step (k of them)."""

    length: np.ndarray  # (k,) policy steps
    reward: np.ndarray  # (k,) sum of the step rewards (Table I, unscaled)
    terms: dict[str, np.ndarray]  # term -> (k,) sum over the episode
    cause: np.ndarray  # (k,) index into CAUSES
    worlds: np.ndarray  # (k,) which worlds
    final: SimStep  # their outputs after the step, before the reset replaced them (a copy)


@dataclass
class StepResult:
    actor: np.ndarray  # (N, actor_dim) float32, observation after the step (and after any reset)
    critic: np.ndarray  # (N, critic_dim) float32
    reward: np.ndarray  # (N,) the step's reward, sum of `terms`
    terminated: np.ndarray  # (N,) bool: fall, deviation or diverged physics
    truncated: np.ndarray  # (N,) bool: the reference ended (a time-out: bootstrap the value)
    terms: dict[str, np.ndarray]  # term -> (N,) weighted value of this step
    episodes: Episodes | None  # the episodes that ended in this step
    unstable: int = 0  # worlds whose physics diverged this step (reset, counted)
    pushed: int = 0  # worlds pushed at the start of this step (RandomizationConfig.push_speed)
    info: dict = field(default_factory=dict)


class TrackingEnv:
    """N worlds tracking references of `bank`. All randomness comes from `seed`."""

    def __init__(self, robot: Robot, bank: ReferenceBank, config: TrackingConfig, num_envs: int, seed: int = 0,
                 sim: BatchedSim | None = None, threads: int | None = None, device: str = "cpu"):
        config.check()
        check_reference_inputs(config.ablation, bank.has_dynamics, bank.source)
        if not (isinstance(num_envs, (int, np.integer)) and num_envs >= 1):
            raise ConfigError(f"number of environments must be a positive integer, got {num_envs}")
        self.robot, self.bank, self.config = robot, bank, config
        self.num_envs, self.nu = int(num_envs), robot.nu
        self.device = str(device)  # the physics backend asked for (opt2skill.sim.devices); the PPO learner follows it
        self.rng = np.random.default_rng(seed)
        grounds, ground = bank.grounds()
        prop_sets, self._prop_set = bank.prop_sets()  # (trajectories,) index of each reference's props
        if sim is None:  # every reference's own ground, then the randomized variants (envs/randomization.py)
            self.terrains = randomization.terrains(config.randomization, grounds, bank.xy_range, seed)
            self.sim = make_sim(robot, self.num_envs, SimConfig(nsubstep=5, nthread=threads), self.terrains,
                                device=device, prop_sets=prop_sets)  # cpu: C MuJoCo; cuda: MuJoCo Warp (docs/sim.md)
            self._ground = ground  # (trajectories,) index of each reference's ground in `terrains`
            self._variants = list(range(len(grounds), len(self.terrains)))
        else:  # the caller's terrains (e.g. a terrain sweep) replace the references' flat floor
            if not all(isinstance(g, Flat) for g in grounds) or sim.props.sets != tuple(prop_sets):
                raise ConfigError("a simulator with its own terrains can only track references made on the flat "
                                  f"floor without props; these were made on {[g.name for g in grounds]} with "
                                  f"props {[p.name for s in prop_sets for p in s]}")
            self.sim, self._ground = sim, np.zeros(bank.num_trajectories, dtype=np.int64)
            self._variants = [i for i, t in enumerate(sim.terrains) if not isinstance(t, Flat)]
        if abs(self.sim.policy_dt - FRAME_DT) > 1e-12:
            raise ConfigError(f"the simulator's policy step is {self.sim.policy_dt} s; references are at {FRAME_DT} s")
        self.terrains = list(self.sim.terrains)
        self._made_on_flat = np.array([isinstance(grounds[g], Flat) for g in ground], dtype=bool)
        self._props_on = self.sim.props.nmoving > 0
        self._prop_used = np.zeros((len(self._prop_set), self.sim.props.nmoving), dtype=bool)  # (trajectories, nmoving)
        for t, i in enumerate(self._prop_set):
            self._prop_used[t] = self.sim.props.used(int(i))
        obs = config.observations
        self.contact_names = bank.contact_names
        self._contact_rows = SensorLayout.from_model(robot.mj_model, robot.config).contact_rows(self.contact_names)
        self.layout: ObservationLayout = layout(obs, self.nu, len(self.contact_names), self.sim.props.nmoving)
        ee_names = list(robot.config.end_effectors)
        self._ee_index = np.array([ee_names.index(e) for e in obs.end_effectors])
        self.default_pose = robot.config.default_pose.astype(np.float64)
        self.action_scale = config.actions.scale
        self._kin_cols, self._dyn_cols = bank.kin_cols, bank.dyn_cols

        n, nu = self.num_envs, self.nu
        self.traj = np.zeros(n, dtype=np.int64)  # table trajectory of each world
        self.frame = np.zeros(n, dtype=np.int64)  # current reference frame t
        self.start_frame = np.zeros(n, dtype=np.int64)
        self.steps = np.zeros(n, dtype=np.int64)  # policy steps in the episode
        self._row = np.zeros(n, dtype=np.int64)
        self._last_row = np.zeros(n, dtype=np.int64)
        self._terms = tuple(config.rewards.terms())
        self._ep_reward = np.zeros(n)
        self._ep_terms = np.zeros((n, len(self._terms)))
        self.action_1 = np.zeros((n, nu))  # a_{t-1}
        self.action_2 = np.zeros((n, nu))  # a_{t-2}
        self._act_hist = StridedHistory(n, nu, obs.history, obs.stride)
        self._q_hist = StridedHistory(n, nu, obs.history, obs.stride)
        self._q_hist_noisy = StridedHistory(n, nu, obs.history, obs.stride)
        self._noise_share = np.ones((n, 1))  # each world's share of the noise (NoiseConfig.per_world_min)
        self._push_countdown = np.zeros(n, dtype=np.int64)  # policy steps until each world's next push
        self.starts = StartSampler(config.episodes, bank.length, FRAME_DT)  # where new episodes begin
        self.set_progress(0.0)
        self.m: Measurement | None = None
        self.state: SimStep | None = None  # the latest simulator outputs (privileged state, e.g. qpos, qvel)
        self.readings: Readings | None = None  # what the latest actor observation read (noise included)
        self.reset()

    # ------------------------------------------------------------------ public

    @property
    def actor_dim(self) -> int:
        return self.layout.actor_dim

    @property
    def critic_dim(self) -> int:
        return self.layout.critic_dim

    def set_progress(self, progress: float) -> None:
        """Training progress in [0, 1]: sets the curriculum's noise and penalty factors and the width of
        the randomization drawn at the next resets."""
        self.progress = float(min(max(progress, 0.0), 1.0))
        curriculum = self.config.curriculum
        self.noise_factor, self.penalty_factor = curriculum.factors(self.progress)
        self.randomization_width = curriculum.randomization_width(self.progress)
        self._randomization = self.config.randomization.narrowed(self.randomization_width)

    def reference_index(self) -> tuple[np.ndarray, np.ndarray]:
        """(dataset position of each world's trajectory, its current frame t)."""
        return self.bank.positions[self.traj], self.frame.copy()

    def contact_wrenches(self, out: SimStep) -> tuple[np.ndarray, np.ndarray]:
        """MEAN wrenches (N, ncontacts, 6) on the references' contacts (a point contact's torque 0) and
        whether each touches something (N, ncontacts), LAST, from simulator outputs `out`."""
        rows = self._contact_rows
        wrench = contact_wrenches(out.contact_wrench_mean, out.point_force_mean, rows)
        return wrench, np.concatenate([out.contact_found, out.point_found], axis=1)[:, rows] > 0

    def actions_for_targets(self, targets: np.ndarray) -> np.ndarray:
        """The actions whose PD targets are `targets` (N, nu): the inverse of the action map."""
        return (np.asarray(targets) - self.default_pose) / self.action_scale

    def reset(self) -> tuple[np.ndarray, np.ndarray]:
        """Reset every world; (actor, critic) observations."""
        self.reset_worlds(np.arange(self.num_envs))
        return self.observations()

    def reset_worlds(self, worlds: np.ndarray, trajectories: np.ndarray | None = None,
                     frames: np.ndarray | None = None) -> None:
        """Start new episodes in `worlds`: trajectories (table indices) and start frames given or
        sampled, Table II parameters re-sampled, histories filled with the start state."""
        worlds = np.asarray(worlds, dtype=np.int64)
        k = len(worlds)
        if k == 0:
            return
        bank = self.bank
        if trajectories is None and frames is None:
            traj, frames = self.starts.sample(self.rng, k)
        else:
            traj = self.rng.integers(0, bank.num_trajectories, k) if trajectories is None else np.asarray(trajectories)
            if frames is None:
                frames = self.starts.frames(self.rng, traj)
        frames = np.asarray(frames, dtype=np.int64)
        if np.any(traj < 0) or np.any(traj >= bank.num_trajectories) or np.any(frames < 0) or np.any(
                frames > bank.length[traj] - 2):
            raise ConfigError("reset: trajectory or start frame out of range")
        rows = bank.start[traj] + frames
        qpos, qvel = bank.state(rows)
        params = randomization.sample_params(self.rng, k, self.sim.nbody, self.nu, self._randomization,
                                             self._variants, self._ground[traj], self._made_on_flat[traj])
        params.kp_factor *= self.config.actions.kp_scale
        params.props = self._prop_set[traj]
        targets = qpos[:, 7:]
        prop_pose, prop_vel = bank.prop_state(rows) if self._props_on else (None, None)
        out = self.sim.reset(worlds, qpos, qvel, targets=targets, params=params, prop_pose=prop_pose, prop_vel=prop_vel)
        m = measure(out, self.sim.z_offset[worlds], self._ee_index, self._contact_rows)
        if self.m is None:  # first reset of every world
            self.m, self.state = m, out
        else:
            self.m.assign(worlds, m)
            self.state.assign(worlds, out)
        self.traj[worlds], self.frame[worlds], self.start_frame[worlds] = traj, frames, frames
        self._row[worlds] = rows
        self._last_row[worlds] = bank.start[traj] + bank.length[traj] - 1
        self.steps[worlds] = 0
        self._ep_reward[worlds] = 0.0
        self._ep_terms[worlds] = 0.0
        if self._pushes_on():  # no draws otherwise: a run without pushes keeps its random stream
            self._push_countdown[worlds] = self._push_intervals(k)
        held = self.actions_for_targets(targets)  # the action that held the start pose
        self.action_1[worlds] = held
        self.action_2[worlds] = held
        self._act_hist.reset(worlds, held)
        self._q_hist.reset(worlds, m.joint_pos)
        noise = self.config.observations.noise
        if noise.per_world_min < 1:  # no draws otherwise: a run at full noise keeps its random stream
            self._noise_share[worlds, 0] = self.rng.uniform(noise.per_world_min, 1.0, k)
        sigma = (self.noise_factor * self._noise_share[worlds] * noise.joint_pos)[:, :, None]
        depth = self._q_hist_noisy.depth
        self._q_hist_noisy.reset(worlds, m.joint_pos[:, None, :] + sigma * self.rng.standard_normal((k, depth, self.nu)))
        self._kp, self._kd, self._limit = self.sim.gains()

    def fail_worlds(self, worlds: np.ndarray) -> None:
        """End these worlds' episodes as failures where they stand (e.g. a teacher lost them: the
        start sampling learns where) and start new ones."""
        worlds = np.asarray(worlds, dtype=np.int64)
        self.starts.record(self.traj[worlds], self.frame[worlds], np.ones(len(worlds), dtype=bool))
        self.reset_worlds(worlds)

    def step(self, actions: np.ndarray) -> StepResult:
        cfg = self.config
        a = np.clip(np.asarray(actions, dtype=np.float64), -cfg.actions.clip, cfg.actions.clip)
        if a.shape != (self.num_envs, self.nu):
            raise ConfigError(f"actions must have shape {(self.num_envs, self.nu)}, got {a.shape}")
        pushed = self._push()
        out = self.sim.step(self.default_pose + self.action_scale * a)
        m = measure(out, self.sim.z_offset, self._ee_index, self._contact_rows)
        bank = self.bank
        kin, dyn = bank.kin[self._row + 1], bank.dyn[self._row]  # frame t + 1 (state), frame t (held over the step)
        ctx = StepContext(m, _columns(kin, self._kin_cols), _columns(dyn, self._dyn_cols), a, self.action_1,
                          self.action_2, self._limit)
        errors = task_errors(ctx)
        terms = reward_terms(cfg.rewards, errors, penalty_values(ctx), self.penalty_factor)
        unstable = out.unstable.copy()  # the resets below overwrite rows of `out`
        if unstable.any():
            for v in terms.values():
                v[unstable] = 0.0
        reward = sum(terms.values())

        self.action_2, self.action_1 = self.action_1, a
        self._act_hist.push(a)
        self._q_hist.push(m.joint_pos)
        sigma = self.noise_factor * cfg.observations.noise.joint_pos
        self._q_hist_noisy.push(m.joint_pos + sigma * self._noise_share * self.rng.standard_normal(m.joint_pos.shape)
                                if sigma else m.joint_pos)
        self.frame += 1
        self._row += 1
        self.steps += 1
        self._ep_reward += reward
        self._ep_terms += np.stack([terms[t] for t in self._terms], axis=1)

        cause = self._causes(m, errors, ctx.kin, unstable, out)
        done = cause >= 0
        truncated = cause == 0
        self.m, self.state = m, out
        episodes = None
        if done.any():
            worlds = np.flatnonzero(done)
            episodes = Episodes(self.steps[worlds].copy(), self._ep_reward[worlds].copy(),
                                {t: self._ep_terms[worlds, i].copy() for i, t in enumerate(self._terms)},
                                cause[worlds].copy(), worlds, out.rows(worlds))
            self.starts.record(self.traj[worlds], self.frame[worlds], ~truncated[worlds])
            self.reset_worlds(worlds)
        actor, critic = self.observations()
        return StepResult(actor, critic, reward, done & ~truncated, truncated, terms, episodes, int(unstable.sum()),
                          pushed)

    def observations(self) -> tuple[np.ndarray, np.ndarray]:
        """(actor (N, actor_dim), critic (N, critic_dim)) float32 of the current state."""
        m, bank, obs_cfg = self.m, self.bank, self.config.observations
        kin = _columns(bank.kin[self._row + obs_cfg.reference_offset], self._kin_cols)
        dyn = _columns(bank.dyn[self._row], self._dyn_cols)
        values = {
            "base_pos": m.base_pos, "base_quat": m.base_quat, "base_lin_vel": m.base_lin_vel,
            "base_ang_vel": m.base_ang_vel, "projected_gravity": m.gravity, "joint_pos_history": self._q_hist.read(),
            "joint_vel": m.joint_vel, "ee_pos": m.ee_pos, "action_history": self._act_hist.read(),
            "contact_force": m.force_heading, "joint_torque": m.torque, "kp": self._kp, "kd": self._kd,
            "ref_base_pos": kin["base_pos"], "ref_base_quat": kin["base_quat"], "ref_base_lin_vel": kin["base_lin_vel"],
            "ref_base_ang_vel": kin["base_ang_vel"], "ref_joint_pos": kin["joint_pos"], "ref_joint_vel": kin["joint_vel"],
            "ref_ee_pos": kin["ee_pos"], "ref_contact_force": dyn["force_heading"], "ref_joint_torque": dyn["joint_torque"],
        }
        if self._props_on:
            values["prop_pos_error"] = self._prop_offsets(self.state, self._row).reshape(self.num_envs, -1)
        critic = fill(np.empty((self.num_envs, self.critic_dim), np.float32), self.layout.critic, values)
        noise, f = obs_cfg.noise, self.noise_factor * self._noise_share
        if self.noise_factor > 0:
            z = self.rng.standard_normal((self.num_envs, 9 + self.nu))
            values["base_lin_vel"] = m.base_lin_vel + f * noise.base_lin_vel * z[:, 0:3]
            values["base_ang_vel"] = m.base_ang_vel + f * noise.base_ang_vel * z[:, 3:6]
            values["projected_gravity"] = m.gravity + f * noise.gravity * z[:, 6:9]
            values["joint_vel"] = m.joint_vel + f * noise.joint_vel * z[:, 9:]
        values["joint_pos_history"] = self._q_hist_noisy.read()
        self.readings = Readings(self._q_hist_noisy.newest().copy(), values["joint_vel"], values["base_lin_vel"],
                                 values["base_ang_vel"], values["projected_gravity"])
        actor = fill(np.empty((self.num_envs, self.actor_dim), np.float32), self.layout.actor, values)
        return actor, critic

    def close(self) -> None:
        self.sim.close()

    def __enter__(self) -> TrackingEnv:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ internals

    def _pushes_on(self) -> bool:
        r = self._randomization
        return r.enabled and r.push_speed > 0

    def _push_intervals(self, k: int) -> np.ndarray:
        """Policy steps until the next push of k worlds (a world reset while pushes were off has 0: it
        is pushed at the first step after they come on)."""
        lo, hi = self.config.randomization.push_interval
        return np.maximum(np.rint(self.rng.uniform(lo, hi, k) / self.sim.policy_dt), 1).astype(np.int64)

    def _push(self) -> int:
        """Push the worlds whose countdown ran out: a horizontal base-velocity change (world frame) of
        uniform direction and a speed uniform in [0, push_speed]; the number pushed."""
        if not self._pushes_on():
            return 0
        self._push_countdown -= 1
        due = np.flatnonzero(self._push_countdown <= 0)
        if len(due) == 0:
            return 0
        k = len(due)
        speed = self._randomization.push_speed * self.rng.random(k)
        heading = self.rng.uniform(-np.pi, np.pi, k)
        velocity = np.stack([speed * np.cos(heading), speed * np.sin(heading), np.zeros(k)], axis=1)
        self.sim.push(due, velocity)
        self._push_countdown[due] = self._push_intervals(k)
        return k

    def prop_error(self, out: SimStep, rows: np.ndarray) -> np.ndarray:
        """(N,) largest distance (m) of a world's free props from their reference positions at `rows`
        (each world's reference row)."""
        if not self._props_on:
            return np.zeros(self.num_envs)
        return np.linalg.norm(self._prop_offsets(out, rows), axis=-1).max(axis=1)

    def _prop_offsets(self, out: SimStep, rows: np.ndarray) -> np.ndarray:
        """(N, nmoving, 3) moving props' positions minus their reference positions at `rows` (lifted by the
        world's z offset, as the props were at reset), world axes; 0 in unused slots."""
        ref = self.bank.prop_pose[rows, :, :3].astype(np.float64)
        ref[..., 2] += self.sim.z_offset[:, None]
        return np.where(self._prop_used[self.traj][..., None], out.prop_pose[..., :3] - ref, 0.0)

    def _causes(self, m: Measurement, errors: dict[str, np.ndarray], kin: dict[str, np.ndarray],
                unstable: np.ndarray, out: SimStep) -> np.ndarray:
        """Index into CAUSES of why each world's episode ends after this step, -1 if it goes on.
        A world that ends for several reasons gets the last one set below (divergence wins)."""
        t = self.config.terminations
        cause = np.full(self.num_envs, -1)
        cause[self._row >= self._last_row] = 0
        if t.min_height:
            cause[m.base_pos[:, 2] < t.min_height] = 1
        if t.max_height_error:
            cause[np.abs(errors["base_pos"][:, 2]) > t.max_height_error] = 2
        if t.max_orientation_error:
            ori = errors["base_ori"]
            cause[np.einsum("ij,ij->i", ori, ori) > t.max_orientation_error ** 2] = 3
        if t.max_xy_error:
            xy = errors["base_pos"][:, :2]
            cause[np.einsum("ij,ij->i", xy, xy) > t.max_xy_error ** 2] = 4
        if t.max_prop_error and self._props_on:  # a box dropped or knocked off: a failure, like a fall
            cause[self.prop_error(out, self._row) > t.max_prop_error] = 6
        cause[unstable] = 5
        return cause


def _columns(block: np.ndarray, cols: dict[str, slice]) -> dict[str, np.ndarray]:
    return {name: block[:, s] for name, s in cols.items()}
