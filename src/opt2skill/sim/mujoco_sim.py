"""The C MuJoCo backend: N worlds stepped by MuJoCo's own batch (`mujoco.batch.Batch`) on its thread pool.

Each world has its own MjModel copy (its randomized parameters, terrain and props), given to the batch
with `set_models`; each pool thread has one MjData. A policy step is one `Batch.rollout` call of S
physics steps for all worlds, with the per-physics-step PD targets of every world (action delay
included) as its open-loop controls. The servos compute u = Kp (q* - q) - Kd qd, clipped to the
torque limit, at every physics step.

Between calls a world's integration state (time, qpos, qvel, act, history, warm start, controls, ...)
is one row of the batch's state, which the batch loads and saves around each call without copies
through Python. Each policy step starts from a zero constraint warm start, so the result of a policy
step is a function of the row's physics state, the world's model and its controls alone: the same
numbers as `mujoco.rollout` from the row's full physics state, which this backend used before.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import mujoco
import numpy as np
from mujoco import batch as mj_batch

from opt2skill.errors import ConfigError
from opt2skill.model.robot import Robot
from opt2skill.scene.ground import TerrainScene
from opt2skill.scene.props import Prop
from opt2skill.scene.slots import PropSlots
from opt2skill.scene.terrain import Flat, Terrain
from opt2skill.sim.base import HostBookkeeping, SimConfig, SimStep, checked_array
from opt2skill.sim.delay import ActionDelay
from opt2skill.sim.outputs import OutputDecoder
from opt2skill.sim.params import NominalModel, WorldParams

INTEGRATION = mujoco.mjtState.mjSTATE_INTEGRATION.value
CTRL = mujoco.mjtState.mjSTATE_CTRL.value


class MujocoBatchedSim(HostBookkeeping):
    """Batched C MuJoCo. All worlds start at the robot's stand pose on terrain 0 with nominal parameters."""

    def __init__(
        self,
        robot: Robot,
        nworld: int,
        config: SimConfig | None = None,
        terrains: Sequence[Terrain] = (Flat(),),
        prop_sets: Sequence[Sequence[Prop]] = ((),),
    ):
        if not (isinstance(nworld, (int, np.integer)) and nworld >= 1):
            raise ConfigError(f"number of worlds must be a positive integer, got {nworld}")
        self.robot, self.nworld = robot, int(nworld)
        self.config = config or SimConfig()
        self._scene = TerrainScene(terrains)
        self.terrains = self._scene.terrains
        self.props = PropSlots(prop_sets)
        spec = robot.mj_spec()
        self._scene.add_to(spec)
        self.props.add_to(spec)
        base = robot.compile(spec)
        self._scene.bind(base)
        self.props.bind(base, robot.nq)
        if self.config.physics_dt is not None:
            base.opt.timestep = self.config.physics_dt
        self._dt = float(base.opt.timestep)
        self.nbody, self.nu = base.nbody, base.nu
        self._max_delay_steps = int(round(self.config.max_delay / self._dt))
        self._nominal = NominalModel(base)
        self._decoder = OutputDecoder(robot, base)
        self._corners = np.array([[robot.site_id(s) for s in foot.corner_sites] for foot in robot.config.feet])
        self.models = [copy.deepcopy(base) for _ in range(self.nworld)]

        self._batch = mj_batch.Batch(base, self.nworld, nthread=self.config.threads)
        self._batch.set_models(self.models)
        self._scratch = mujoco.MjData(base)
        S = self.nsubstep
        self._rows = self._batch.state  # (N, nstate) integration state, live
        # Views of the rows (writes are the worlds' state at the next call): the robot's coordinates
        # come first in qpos and qvel, then the free props' 7 positions and 6 velocities, then the doors' hinges.
        self._time, self._qpos_all, self._qvel_all = (self._batch.bind(f) for f in ("time", "qpos", "qvel"))
        self._warm_start = self._batch.bind("qacc_warmstart")
        self._record = {"sensordata": np.zeros((self.nworld, S, base.nsensordata))}
        self._out_sensor = self._record["sensordata"]
        nq, nv = robot.nq, robot.mj_model.nv
        nfree = self.props.nfree
        self._prop_qpos, self._prop_qvel = slice(nq, nq + 7 * nfree), slice(nv, nv + 6 * nfree)
        self._hinge_qpos, self._hinge_qvel = slice(nq + 7 * nfree, base.nq), slice(nv + 6 * nfree, base.nv)
        self._delay = ActionDelay(self.nworld, base.nu, S, self._max_delay_steps)
        self._params = WorldParams.nominal(self.nworld, base.nbody, base.nu)
        self._z_offset = np.zeros(self.nworld)
        self._gravity = np.tile(base.opt.gravity, (self.nworld, 1))
        self._last: SimStep | None = None

        everyone = np.arange(self.nworld)
        self.set_params(everyone, self._params)
        stand = np.broadcast_to(robot.stand_qpos, (self.nworld, nq))
        self._last = self.reset(everyone, stand, np.zeros((self.nworld, nv)))

    # ---------------------------------------------------------------- interface

    @property
    def state(self) -> np.ndarray:
        """(N, nstate) integration state of every world (mjSTATE_INTEGRATION layout), a copy."""
        return self._rows.copy()

    def set_params(self, worlds: np.ndarray, params: WorldParams) -> None:
        worlds = self.check_worlds(worlds)
        m = self.models[0]
        p = params.checked(len(worlds), m.nbody, m.nu, self.config.max_delay, len(self.terrains),
                           len(self.props.sets))
        for row, w in enumerate(worlds):  # per reset, never per step
            model = self.models[w]
            if self.props:
                self._nominal.apply(model, p, row, lambda mm: self.props.apply(mm, int(p.props[row]),
                                                                               float(p.friction_scale[row])))
            else:
                self._nominal.apply(model, p, row)
            self._scene.apply(model, int(p.terrain[row]))
        self._batch.set_models(self.models)  # the batch's contract after its models are edited
        self._delay.set_delay(worlds, np.rint(p.delay / self._dt).astype(int))
        self._params.assign(worlds, p)
        self._gravity[worlds] = self._nominal.gravity * p.gravity_scale[:, None]

    def reset(
        self,
        worlds: np.ndarray,
        qpos: np.ndarray,
        qvel: np.ndarray,
        targets: np.ndarray | None = None,
        params: WorldParams | None = None,
        prop_pose: np.ndarray | None = None,
        prop_vel: np.ndarray | None = None,
    ) -> SimStep:
        nq, nv = self.robot.nq, self.robot.mj_model.nv
        worlds, qpos, qvel, targets = self.checked_reset(worlds, qpos, qvel, targets, nq, nv)
        k = len(worlds)
        if params is not None:
            self.set_params(worlds, params)
        prop_q, prop_v = self._prop_states(worlds, prop_pose, prop_vel)
        d = self._scratch
        sensors = np.zeros((k, 1, self.models[0].nsensordata))
        for row, w in enumerate(worlds):  # per reset, never per step
            model = self.models[w]
            mujoco.mj_resetData(model, d)  # time 0, act and history cleared
            d.qpos[:nq], d.qpos[nq:] = qpos[row], prop_q[row]
            d.qvel[:nv], d.qvel[nv:] = qvel[row], prop_v[row]
            self._z_offset[w] = self._lift_onto_terrain(model, d, w)
            d.qpos[2] += self._z_offset[w]
            free = self.props.used(int(self._params.props[w]))[: self.props.nfree]
            d.qpos[nq + 2 : nq + 7 * self.props.nfree : 7] += self._z_offset[w] * free  # props held or set down
            d.ctrl[:] = targets[row] if targets is not None else d.qpos[7:nq]
            mujoco.mj_forward(model, d)
            mujoco.mj_getState(model, d, self._rows[w], INTEGRATION)
            sensors[row, 0] = d.sensordata
        self._delay.clear(worlds, targets)
        qpos_all, qvel_all = self._qpos_all[worlds], self._qvel_all[worlds]
        out = self._decoder.decode(
            self._time[worlds], qpos_all[:, :nq], qvel_all[:, :nv], qvel_all[:, :nv], sensors, 0.0, self.policy_dt,
            self._gravity[worlds], *self._prop_outputs(qpos_all, qvel_all, worlds),
        )
        if self._last is not None:
            self._last.assign(worlds, out)
        return out

    def step(self, targets: np.ndarray) -> SimStep:
        targets = self.checked_targets(targets)
        nq, nv = self.robot.nq, self.robot.mj_model.nv
        start, start_time, start_qvel = self._rows.copy(), self._time.copy(), self._qvel_all[:, :nv].copy()
        control = self._delay.sequence(targets)
        self._warm_start[:] = 0.0
        try:
            self._batch.rollout(self.nsubstep, control, control_spec=CTRL, record=("sensordata",), out=self._record)
        except mj_batch.SimulationError:
            pass  # MuJoCo raised in those worlds: they kept their state, which the time check below flags
        out = self._decoder.decode(
            self._time.copy(), self._qpos_all[:, :nq].copy(), self._qvel_all[:, :nv].copy(), start_qvel,
            self._out_sensor, self._dt, self.policy_dt, self._gravity,
            *self._prop_outputs(self._qpos_all, self._qvel_all, np.arange(self.nworld)),
        )
        bad = self._diverged(start_time)
        if bad.any():
            self._hold(bad, start, out)
        self._last = out
        return out

    def push(self, worlds: np.ndarray, velocity: np.ndarray) -> None:
        worlds = self.check_worlds(worlds)
        velocity = checked_array("push velocity", velocity, (len(worlds), 3))
        self._qvel_all[worlds, :3] += velocity  # the free joint's linear velocity is in the world frame

    def close(self) -> None:
        self._batch = None

    # ---------------------------------------------------------------- internals

    def _diverged(self, time_start: np.ndarray) -> np.ndarray:
        """Worlds whose step went wrong: MuJoCo reset them, stopped them (a warning) or raised in them
        (time did not advance by S physics steps), or a state or reading is not finite, or a speed
        exceeds the bound."""
        expected = time_start + self.nsubstep * self._dt
        with np.errstate(invalid="ignore", over="ignore"):
            ok = np.abs(self._time - expected) <= 0.5 * self._dt
            ok &= np.abs(self._qvel_all).max(axis=1) <= self.config.max_speed  # False for NaN
            ok &= np.isfinite(self._rows.sum(axis=1) + self._out_sensor.sum(axis=(1, 2)))  # sums keep NaN and inf
        return ~ok

    def _prop_states(self, worlds: np.ndarray, pose, vel) -> tuple[np.ndarray, np.ndarray]:
        """qpos (k, 7 nfree + nhinged) and qvel (k, 6 nfree + nhinged) of the moving props of
        `worlds`: the given poses (k, nmoving, 7) and velocities (k, nmoving, 6) in the slots their
        prop sets use (each set's rest poses and zero velocity when not given), every unused slot
        parked at rest; a door's angle from its pose, its rate the angular velocity's z."""
        k, n, nf = len(worlds), self.props.nmoving, self.props.nfree
        sets = self._params.props[worlds]
        rest = np.stack([self.props.rest_poses(int(i)) for i in sets]) if n else np.zeros((k, 0, 7))
        used = np.stack([self.props.used(int(i)) for i in sets]) if n else np.zeros((k, 0), dtype=bool)
        q = rest if pose is None else np.where(used[..., None], checked_array("prop_pose", pose, (k, n, 7)), rest)
        q[..., 3:] /= np.linalg.norm(q[..., 3:], axis=-1, keepdims=True)
        v = np.zeros((k, n, 6)) if vel is None else checked_array("prop_vel", vel, (k, n, 6)) * used[..., None]
        angles = np.stack([self.props.door_angles(int(i), q[row, nf:]) for row, i in enumerate(sets)]) if k else np.zeros((0, n - nf))
        return (np.concatenate([q[:, :nf].reshape(k, 7 * nf), angles], axis=1),
                np.concatenate([v[:, :nf].reshape(k, 6 * nf), v[:, nf:, 5]], axis=1))

    def _prop_outputs(self, qpos: np.ndarray, qvel: np.ndarray, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Moving props' poses (N, nmoving, 7) and velocities (N, nmoving, 6) of `worlds` from their
        whole qpos and qvel: the boxes', then the doors' hinge frames (angular velocity about z their rate)."""
        nf, k = self.props.nfree, len(qpos)
        pose = np.zeros((k, self.props.nmoving, 7))
        vel = np.zeros((k, self.props.nmoving, 6))
        pose[:, :nf] = qpos[:, self._prop_qpos].reshape(k, nf, 7)
        vel[:, :nf] = qvel[:, self._prop_qvel].reshape(k, nf, 6)
        if self.props.nhinged:
            angles = qpos[:, self._hinge_qpos]
            sets = self._params.props[worlds]
            for i in np.unique(sets):
                rows = sets == i
                pose[rows, nf:] = self.props.door_poses(int(i), angles[rows])
            vel[:, nf:, 5] = qvel[:, self._hinge_qvel]
        return pose, vel

    def _hold(self, bad: np.ndarray, start: np.ndarray, out: SimStep) -> None:
        """Isolate diverged worlds: back to their state before the step, outputs of that state."""
        self._rows[bad] = start[bad]
        out.assign(bad, self._last.rows(bad))
        out.unstable[:] = bad

    def _lift_onto_terrain(self, model: mujoco.MjModel, d: mujoco.MjData, world: int) -> float:
        """Height to add so no foot is inside the terrain and the feet are not lowered below it.

        With c_f the lowest sole corner of foot f and h_f the highest terrain under it, the lift is
        max(max_f (h_f - c_f), min_f h_f): a stance foot (c = 0) lands on the highest point under it,
        a swing foot keeps its clearance. On the flat plane it is 0, and so it is for a world whose
        `lift` is off (its state was made on this terrain and already stands on it).
        """
        terrain = self.terrains[int(self._params.terrain[world])]
        if isinstance(terrain, Flat) or not self._params.lift[world]:
            return 0.0
        mujoco.mj_kinematics(model, d)
        corners = d.site_xpos[self._corners]  # (nfeet, 4, 3)
        heights = terrain.max_height(corners[..., :2].min(axis=1), corners[..., :2].max(axis=1))
        lowest = corners[..., 2].min(axis=1)
        return float(max((heights - lowest).max(), heights.min()))
