"""The MuJoCo Warp backend: N worlds as one batched `mujoco_warp` Data, on a GPU (or Warp's CPU device).

Same scene, servos, action delay, outputs and divergence guard as the C backend (mujoco_sim.py).
The servos are the model's own position actuators (u = Kp (q* - q) - Kd qd, clipped to the torque
limit), evaluated by MuJoCo Warp on the device at every physics step. Per policy step the host
sends the (N, S, nu) control sequence of the action delay once; the S physics steps, the per-step
control switch and the sensor recording run on the device (a CUDA graph on GPUs), without a loop
over worlds anywhere.

Per-world parameters are batched model arrays (leading dimension N): body mass and inertia (with
the derived subtree masses, inverse weights and actuator acc0 recomputed on the device by
`mujoco_warp.set_const`), geom friction, gravity, and the servos' Kp, Kd and torque limits.
MuJoCo Warp keeps collision bits per model, not per world, but geom poses, sizes and the
heightfield a geom shows are per world: each rough terrain gets its own heightfield asset, a
world's ground geoms take the poses and sizes its terrain gives them (the scene's own `apply`, run
once per terrain), and the ground geoms a world does not show are moved 1 km down
(docs/sim.md, "MuJoCo Warp backend").

Physics runs in float32 (MuJoCo Warp's precision); outputs are float64 numpy arrays like the C
backend's, and `device_arrays()` gives torch tensors that share the device memory.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import mujoco
import numpy as np

from opt2skill.errors import ConfigError
from opt2skill.model.robot import Robot
from opt2skill.scene.ground import HFIELD, TerrainScene
from opt2skill.scene.terrain import Flat, Rough, Terrain
from opt2skill.sim.base import HostBookkeeping, SimConfig, SimStep, checked_array
from opt2skill.sim.delay import ActionDelay
from opt2skill.sim.devices import import_warp
from opt2skill.sim.outputs import OutputDecoder
from opt2skill.sim.params import NominalModel, WorldParams

wp, mjw = import_warp()

# Model arrays given one row per world (put_model's batch_sizes). The last four are derived from
# the masses and written by set_const.
GROUND_FIELDS = ("geom_pos", "geom_quat", "geom_size", "geom_aabb", "geom_rbound", "geom_dataid")
BATCHED = ("body_mass", "body_inertia", "geom_friction", "actuator_gainprm", "actuator_biasprm",
           "actuator_forcerange", *GROUND_FIELDS,
           "body_subtreemass", "body_invweight0", "dof_invweight0", "actuator_acc0")
AWAY = -1000.0  # m: where the ground a world does not stand on is moved


@wp.kernel
def _select_control(seq: wp.array3d(dtype=float), j: int, ctrl: wp.array2d(dtype=float)):
    world, u = wp.tid()
    ctrl[world, u] = seq[world, j, u]


@wp.kernel
def _record_sensors(sensordata: wp.array2d(dtype=float), j: int, out: wp.array3d(dtype=float)):
    world, i = wp.tid()
    out[world, j, i] = sensordata[world, i]


class WarpBatchedSim(HostBookkeeping):
    """Batched MuJoCo Warp. All worlds start at the robot's stand pose with nominal parameters.

    `device`: a Warp device ("cuda", "cuda:1", or "cpu" for tests). `nconmax` contacts and `njmax`
    constraint rows are allocated per world; a step that needs more raises (raise them then).
    `graph`: on a GPU, replay the S physics steps as one captured CUDA graph.
    """

    def __init__(
        self,
        robot: Robot,
        nworld: int,
        config: SimConfig | None = None,
        terrains: Sequence[Terrain] = (Flat(),),
        device: str = "cuda",
        nconmax: int = 32,
        njmax: int = 256,
        graph: bool = True,
    ):
        if not (isinstance(nworld, (int, np.integer)) and nworld >= 1):
            raise ConfigError(f"number of worlds must be a positive integer, got {nworld}")
        self.robot, self.nworld = robot, int(nworld)
        self.config = config or SimConfig()
        self.device = wp.get_device(device)
        self._scene = TerrainScene(terrains)
        self.terrains = self._scene.terrains
        spec = robot.mj_spec()
        self._scene.add_to(spec)
        plain = robot.compile(spec)  # one heightfield, as the scene's `apply` expects
        self._scene.bind(plain)
        rough = [i for i, t in enumerate(self.terrains) if isinstance(t, Rough)]
        for i in rough[1:]:  # the scene's own heightfield serves the first rough terrain
            g = self._scene.grid
            spec.add_hfield(name=f"{HFIELD}_{i}", nrow=g.nrow, ncol=g.ncol, size=spec.hfield(HFIELD).size,
                            userdata=[0.0] * (g.nrow * g.ncol))
        base = robot.compile(spec)
        self._scene.bind(base)
        hfield_of = {}  # terrain -> heightfield id
        for n, i in enumerate(rough):
            hid = mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_HFIELD, HFIELD if n == 0 else f"{HFIELD}_{i}")
            adr = base.hfield_adr[hid]
            base.hfield_data[adr:adr + base.hfield_nrow[hid] * base.hfield_ncol[hid]] = self._scene._normalized[i]
            hfield_of[i] = hid
        self._ground, self._ground_table = self._ground_tables(plain, hfield_of)  # same geoms as `base`
        self._corners = np.array([[robot.site_id(s) for s in foot.corner_sites] for foot in robot.config.feet])
        if self.config.physics_dt is not None:
            base.opt.timestep = self.config.physics_dt
        self.model = base  # the nominal host model (worlds differ only in the batched arrays)
        self._dt = float(base.opt.timestep)
        self.nbody, self.nu = base.nbody, base.nu
        self._nominal = NominalModel(base)
        self._decoder = OutputDecoder(robot, base)
        S, N = self.nsubstep, self.nworld
        self._delay = ActionDelay(N, base.nu, S, int(round(self.config.max_delay / self._dt)))
        self._params = WorldParams.nominal(N, base.nbody, base.nu)
        self._z_offset = np.zeros(N)
        self._gravity = np.tile(base.opt.gravity, (N, 1))
        self._graph = None
        self._use_graph = graph and self.device.is_cuda
        self._last: SimStep | None = None

        with wp.ScopedDevice(self.device):
            self.m = mjw.put_model(base, batch_sizes=dict.fromkeys(BATCHED, N))
            self.m.opt.gravity = wp.array(self._gravity, dtype=wp.vec3)
            host = mujoco.MjData(base)
            self.d = mjw.put_data(base, host, nworld=N, nconmax=nconmax, njmax=njmax)
            self._ctrl_seq = wp.zeros((N, S, base.nu), dtype=float)
            self._sensors = wp.zeros((N, S, base.nsensordata), dtype=float)
        self._njmax = njmax

        everyone = np.arange(N)
        self.set_params(everyone, self._params)
        stand = np.broadcast_to(robot.stand_qpos, (N, base.nq))
        self._last = self.reset(everyone, stand, np.zeros((N, base.nv)))

    # ---------------------------------------------------------------- interface

    def set_params(self, worlds: np.ndarray, params: WorldParams) -> None:
        worlds = self.check_worlds(worlds)
        p = params.checked(len(worlds), self.nbody, self.nu, self.config.max_delay, len(self.terrains))
        mass_changed = not np.array_equal(p.mass_scale[:, 1:], self._params.mass_scale[worlds, 1:])
        self._params.assign(worlds, p)
        self._delay.set_delay(worlds, np.rint(p.delay / self._dt).astype(int))
        self._gravity[worlds] = self._nominal.gravity * p.gravity_scale[:, None]
        self._upload_params(mass_changed)

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
        if any(x is not None and np.size(x) for x in (prop_pose, prop_vel)):
            raise ConfigError("the Warp backend simulates no props (docs/sim.md); it has no prop poses to set")
        worlds, qpos, qvel, targets = self.checked_reset(worlds, qpos, qvel, targets, self.model.nq, self.model.nv)
        k = len(worlds)
        if params is not None:
            self.set_params(worlds, params)
        d = self.d
        with wp.ScopedDevice(self.device):
            state = {name: getattr(d, name).numpy() for name in ("time", "qpos", "qvel", "ctrl", "qacc_warmstart")}
            state["time"][worlds] = 0.0
            state["qpos"][worlds] = qpos
            state["qvel"][worlds] = qvel
            state["ctrl"][worlds] = targets if targets is not None else qpos[:, 7:]
            state["qacc_warmstart"][worlds] = 0.0
            for name, value in state.items():
                getattr(d, name).assign(value)
            qpos = qpos.copy()
            lift = self._lift_onto_terrain(worlds)
            self._z_offset[worlds] = lift
            if lift.any():
                qpos[:, 2] += lift
                state["qpos"][worlds, 2] = qpos[:, 2]
                d.qpos.assign(state["qpos"])
            mjw.forward(self.m, d)  # every world: the others' state is unchanged, their readings unused
            sensors = d.sensordata.numpy()[worlds][:, None].astype(np.float64)
        self._delay.clear(worlds, targets)
        out = self._decoder.decode(np.zeros(k), qpos, qvel.copy(), qvel, sensors, 0.0, self.policy_dt,
                                   self._gravity[worlds])
        if self._last is not None:
            self._last.assign(worlds, out)
        return out

    def step(self, targets: np.ndarray) -> SimStep:
        targets = self.checked_targets(targets)
        d = self.d
        with wp.ScopedDevice(self.device):
            start = [d.time.numpy().astype(np.float64), d.qpos.numpy().copy(), d.qvel.numpy().copy()]
            self._ctrl_seq.assign(self._delay.sequence(targets).astype(np.float32))
            d.qacc_warmstart.zero_()  # as the C backend: each policy step from a zero warm start
            self._run_substeps()
            self._check_capacity()
            time = d.time.numpy().astype(np.float64)
            qpos = d.qpos.numpy().astype(np.float64)
            qvel = d.qvel.numpy().astype(np.float64)
            sensors = self._sensors.numpy().astype(np.float64)
        out = self._decoder.decode(time, qpos, qvel, start[2].astype(np.float64), sensors, self._dt, self.policy_dt,
                                   self._gravity)
        bad = self._diverged(start[0], time, qvel, sensors)
        if bad.any():
            self._hold(bad, start, out)
        self._last = out
        return out

    def push(self, worlds: np.ndarray, velocity: np.ndarray) -> None:
        worlds = self.check_worlds(worlds)
        velocity = checked_array("push velocity", velocity, (len(worlds), 3))
        with wp.ScopedDevice(self.device):
            qvel = self.d.qvel.numpy()
            qvel[worlds, :3] += velocity  # the free joint's linear velocity is in the world frame
            self.d.qvel.assign(qvel)

    def device_arrays(self) -> dict:
        """The device state as torch tensors sharing Warp's memory (no copies): time (N,), qpos (N, nq),
        qvel (N, nv), ctrl (N, nu), sensordata (N, S, nsensordata) of the last policy step."""
        d = self.d
        return {"time": wp.to_torch(d.time), "qpos": wp.to_torch(d.qpos), "qvel": wp.to_torch(d.qvel),
                "ctrl": wp.to_torch(d.ctrl), "sensordata": wp.to_torch(self._sensors)}

    def close(self) -> None:
        self._graph = None

    # ---------------------------------------------------------------- internals

    def _upload_params(self, mass_changed: bool) -> None:
        """All worlds' batched model arrays from `_params` (small arrays: one upload per reset)."""
        nom, p, m = self._nominal, self._params, self.m
        mass = p.mass_scale.copy()
        mass[:, 0] = 1.0
        strength = p.motor_strength
        kp = nom.kp * p.kp_factor * strength
        kd = nom.kd * p.kd_factor * strength
        with wp.ScopedDevice(self.device):
            gain, bias = m.actuator_gainprm.numpy(), m.actuator_biasprm.numpy()
            gain[:, :, 0] = kp
            bias[:, :, 1] = -kp
            bias[:, :, 2] = -kd
            m.actuator_gainprm.assign(gain)
            m.actuator_biasprm.assign(bias)
            m.actuator_forcerange.assign(nom.forcerange[None] * strength[:, :, None])
            m.geom_friction.assign(nom.geom_friction[None] * p.friction_scale[:, None, None])
            m.opt.gravity.assign(self._gravity)
            g, table = self._ground, self._ground_table
            for name in GROUND_FIELDS:  # each world's ground geoms as its terrain shows them
                array = getattr(m, name)
                value = array.numpy()
                value[:, g] = table[name][p.terrain]
                array.assign(value)
            # MuJoCo Warp computes the world poses of static geoms once, in put_data: set them there too
            for name, field in (("geom_xpos", "geom_pos"), ("geom_xmat", "xmat")):
                value = getattr(self.d, name).numpy()
                value[:, g] = table[field][p.terrain].reshape(value[:, g].shape)
                getattr(self.d, name).assign(value)
            if mass_changed:
                m.body_mass.assign(nom.body_mass[None] * mass)
                m.body_inertia.assign(nom.body_inertia[None] * mass[:, :, None])
                mjw.set_const(m, self.d)  # subtree masses, inverse weights, acc0 of every world

    def _ground_tables(self, scratch: mujoco.MjModel, hfield_of: dict[int, int]) -> tuple[np.ndarray, dict]:
        """The ground geoms, and per terrain (leading dimension) their pose, size, bounds, heightfield
        and orientation matrix as the scene's `apply` sets them on an MjModel; hidden ones moved AWAY."""
        ground = np.array(sorted(self._scene._ids.values()))
        table = {name: [] for name in (*GROUND_FIELDS, "xmat")}
        for t in range(len(self.terrains)):
            self._scene.apply(scratch, t)
            pos = scratch.geom_pos[ground].copy()
            pos[scratch.geom_contype[ground] == 0, 2] = AWAY
            dataid = scratch.geom_dataid[ground].copy()
            dataid[dataid >= 0] = hfield_of.get(t, dataid[dataid >= 0])
            xmat = np.zeros((len(ground), 9))
            for row, gid in enumerate(ground):
                mujoco.mju_quat2Mat(xmat[row], scratch.geom_quat[gid])
            for name, value in (("geom_pos", pos), ("geom_quat", scratch.geom_quat[ground]),
                                ("geom_size", scratch.geom_size[ground]),
                                ("geom_aabb", scratch.geom_aabb[ground].reshape(-1, 2, 3)),
                                ("geom_rbound", scratch.geom_rbound[ground]), ("geom_dataid", dataid), ("xmat", xmat)):
                table[name].append(np.array(value))
        return ground, {name: np.stack(rows) for name, rows in table.items()}

    def _lift_onto_terrain(self, worlds: np.ndarray) -> np.ndarray:
        """(k,) lift of each world, as the C backend's `_lift_onto_terrain`, from the sole corners of
        the qpos just written (kinematics on the device, a loop over the terrains, not the worlds)."""
        lift = np.zeros(len(worlds))
        which = self._params.terrain[worlds]
        needed = self._params.lift[worlds] & np.array([not isinstance(self.terrains[t], Flat) for t in which], dtype=bool)
        if not needed.any():
            return lift
        mjw.kinematics(self.m, self.d)
        corners = self.d.site_xpos.numpy()[worlds][:, self._corners].astype(np.float64)  # (k, nfeet, 4, 3)
        for index in np.unique(which[needed]):
            rows = np.flatnonzero(needed & (which == index))
            c = corners[rows]
            nfeet = c.shape[1]
            heights = self.terrains[index].max_height(c[..., :2].min(axis=2).reshape(-1, 2),
                                                      c[..., :2].max(axis=2).reshape(-1, 2)).reshape(-1, nfeet)
            lowest = c[..., 2].min(axis=2)
            lift[rows] = np.maximum((heights - lowest).max(axis=1), heights.min(axis=1))
        return lift

    def _substeps(self) -> None:
        d, N, nu, ns = self.d, self.nworld, self.nu, self._sensors.shape[2]
        for j in range(self.nsubstep):
            wp.launch(_select_control, dim=(N, nu), inputs=[self._ctrl_seq, j, d.ctrl])
            mjw.step(self.m, d)
            wp.launch(_record_sensors, dim=(N, ns), inputs=[d.sensordata, j, self._sensors])

    def _run_substeps(self) -> None:
        if not self._use_graph:
            self._substeps()
            return
        if self._graph is None:
            try:
                self._substeps()  # this policy step, eagerly: compiles every kernel before the capture
                with wp.ScopedCapture() as capture:  # records the launches without running them
                    self._substeps()
                self._graph = capture.graph
                return
            except Exception as exc:  # capture unsupported (driver, memory pool): step eagerly
                warnings.warn(f"CUDA graph capture failed ({exc}); stepping without a graph", stacklevel=2)
                self._use_graph = False
                return
        wp.capture_launch(self._graph)

    def _check_capacity(self) -> None:
        d = self.d
        nacon = int(d.nacon.numpy()[0])
        nefc = int(d.nefc.numpy().max())
        if nacon > d.naconmax or nefc > self._njmax:
            raise RuntimeError(f"MuJoCo Warp ran out of room: {nacon} contacts for {d.naconmax} allocated, "
                               f"{nefc} constraint rows in a world for {self._njmax}; raise nconmax / njmax")

    def _diverged(self, time_start, time, qvel, sensors) -> np.ndarray:
        expected = time_start + self.nsubstep * self._dt
        with np.errstate(invalid="ignore", over="ignore"):
            ok = np.abs(time - expected) <= 0.5 * self._dt
            ok &= np.abs(qvel).max(axis=1) <= self.config.max_speed  # False for NaN
            ok &= np.isfinite(qvel.sum(axis=1) + sensors.sum(axis=(1, 2)))
        return ~ok

    def _hold(self, bad: np.ndarray, start: list[np.ndarray], out: SimStep) -> None:
        """Diverged worlds back to their state before the step, outputs of that state."""
        with wp.ScopedDevice(self.device):
            for array, before in zip((self.d.time, self.d.qpos, self.d.qvel), start):
                now = array.numpy()
                now[bad] = before[bad]
                array.assign(now)
        out.assign(bad, self._last.rows(bad))
        out.unstable[:] = bad
