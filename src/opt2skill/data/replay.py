"""Replay a reference in MuJoCo: reference-torque feedforward plus PD at the physics rate (1 kHz).

At every physics step the servos receive the target `q_ref + (tau_ref + kd qd_ref) / kp`, so the
actuator applies exactly `tau_ref + kp (q_ref - q) + kd (qd_ref - qd)`, clipped to the torque
limits (docs/conventions.md: feedforward through the servo target). The references are the 200 Hz
frames: joint positions and velocities interpolated linearly, torques held over each frame.

An open-loop replay of a long walk drifts and falls even when the reference is dynamically exact
(the feedforward is open loop; the PD only corrects joint angles, not balance). So a replay is run
twice: once over the whole motion (the time to fall is reported), and as windows of fixed length,
each restarted from the reference state, that tile the motion (a reference that cannot be followed
for a few seconds from its own state is suspicious). docs/data.md gives the figures behind this.

The replay runs in the record's scene (its terrain and props, `opt2skill.scene.build_model`). The
robot's state leads the scene model's; props start where the scene puts them at every restart.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import mujoco.rollout
import numpy as np
import pinocchio as pin

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.geometry import quat_error
from opt2skill.model.convert import qpos_mj_to_pin, qvel_mj_to_pin
from opt2skill.model.mujoco_model import sensor_slice
from opt2skill.model.robot import Robot
from opt2skill.model.sensors import SensorLayout
from opt2skill.scene.build import build_model
from opt2skill.scene.props import Door
from opt2skill.trajopt.native import load as load_native


@dataclass(frozen=True)
class ReplaySettings:
    window: float = 1.0  # s, length of each restarted replay window (docs/data.md: why 1 s)
    fall_height: float = 0.25  # m: fallen when the base is this much lower than the reference
    fall_angle: float = 0.5  # rad: fallen when the base orientation is this far from the reference
    velocity_reference: bool = True  # PD on (qd_ref - qd) rather than on -qd
    # The motors also supply the MuJoCo joints' damping and friction loss, which the rigid-body
    # reference torques leave out (docs/data.md): D qd + f tanh(qd / friction_smoothing).
    joint_losses: bool = True
    friction_smoothing: float = 0.05  # rad/s
    # Feedback replay: the servos' own PD tracks the reference under the feedback torque (True), or
    # is cancelled so the feedback torque acts alone (False). docs/data.md has the measurements.
    feedback_pd: bool = True


@dataclass(frozen=True)
class Rollout:
    """One replay from a reference frame: what happened, until the fall if there was one."""

    start: float  # s, reference time of the start
    duration: float  # s replayed
    fall_time: float | None  # s after the start, None when the robot stayed up
    joint_rms: float  # rad, joint position error RMS until the fall
    base_error: float  # m, largest base position error until the fall
    foot_error: float  # m, largest sole position error until the fall


def _interp(values: np.ndarray, frac: np.ndarray) -> np.ndarray:
    k0 = np.clip(np.floor(frac).astype(int), 0, len(values) - 1)
    k1 = np.minimum(k0 + 1, len(values) - 1)
    w = (frac - k0).reshape(-1, *([1] * (values.ndim - 1)))
    return (1.0 - w) * values[k0] + w * values[k1]


def _interp_quat(quat: np.ndarray, frac: np.ndarray) -> np.ndarray:
    k0 = np.clip(np.floor(frac).astype(int), 0, len(quat) - 1)
    k1 = np.minimum(k0 + 1, len(quat) - 1)
    q1 = quat[k1] * np.sign(np.sum(quat[k0] * quat[k1], axis=-1, keepdims=True) + 1e-300)
    w = (frac - k0)[:, None]
    q = (1.0 - w) * quat[k0] + w * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


class Replayer:
    """Replays one trajectory on one robot (single-threaded: one per validation worker)."""

    def __init__(self, robot: Robot, traj: Trajectory, settings: ReplaySettings = ReplaySettings(),
                 use_compiled: bool = True, all_sensors: bool = True):
        self.robot, self.traj, self.settings = robot, traj, settings
        # The feedback loop in C++ where the compiled module loads (the same states to round-off, so
        # not a setting: datasets' identities hold the settings).
        self.use_compiled = use_compiled
        feet = [f.name for f in robot.config.feet]
        # The replays' own figures read only the soles' positions. Without `all_sensors` the model
        # computes nothing else (the other sensors are about a tenth of a Digit step, and change
        # no state); `layout` then is None and the returned sensors hold the soles' positions alone.
        self.model = build_model(robot, traj.scene, None if all_sensors else [f"ee_{n}" for n in feet])
        self.data = mujoco.MjData(self.model)
        self.nq, self.nv = robot.nq, robot.nv  # the robot's part of the scene's qpos and qvel
        self.dt = float(self.model.opt.timestep)
        self.layout = SensorLayout.from_model(self.model, robot.config) if all_sensors else None
        self.foot_columns = np.stack([np.arange(s.start, s.stop) for s in
                                      (sensor_slice(self.model, f"ee_{n}") for n in feet)])  # (feet, 3)
        self.foot_ref = [traj.ee_names.index(n) for n in feet]
        self.damping = self.model.dof_damping[6 : self.nv].copy()
        self.frictionloss = self.model.dof_frictionloss[6 : self.nv].copy()

    def _frac(self, start_frame: int, nstep: int, offset: float = 0.0) -> np.ndarray:
        """Fractional frame index at each physics step (plus `offset` steps)."""
        return start_frame + (np.arange(nstep) + offset) * self.dt / FRAME_DT

    def controls(self, start_frame: int, nstep: int) -> np.ndarray:
        cfg, tr = self.robot.config, self.traj
        frac = self._frac(start_frame, nstep)
        q_ref = _interp(tr.qpos[:, 7:], frac)
        tau = tr.joint_torque[np.clip(np.floor(frac + 1e-9).astype(int), 0, tr.num_frames - 1)]
        qd_ref = _interp(tr.qvel[:, 6:], frac)
        tau = tau + self._joint_losses(qd_ref)
        if self.settings.velocity_reference:
            tau = tau + cfg.kd * qd_ref
        return q_ref + tau / cfg.kp

    def _joint_losses(self, qd: np.ndarray) -> np.ndarray:
        """Torque the motors add to overcome the joints' damping and friction loss at speed qd."""
        if not self.settings.joint_losses:
            return np.zeros_like(qd)
        s = self.settings.friction_smoothing
        return self.damping * qd + self.frictionloss * np.tanh(qd / s)

    def initial_state(self, frame: int) -> np.ndarray:
        d = self.data
        mujoco.mj_resetData(self.model, d)  # props at their scene poses, at rest
        d.qpos[: self.nq] = self.traj.qpos[frame]
        d.qvel[: self.nv] = self.traj.qvel[frame]
        self._open_doors(frame)
        state = np.empty(mujoco.mj_stateSize(self.model, mujoco.mjtState.mjSTATE_FULLPHYSICS))
        mujoco.mj_getState(self.model, d, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        return state

    def _open_doors(self, frame: int) -> None:
        """Doors at the reference's angle and rate of `frame` (a restart with the hands on an open
        door would otherwise put them inside its closed panel); free boxes stay at their scene poses."""
        for prop in self.traj.scene.props:
            if isinstance(prop, Door) and prop.name in self.traj.prop_poses:
                angle = prop.angle_of(self.traj.prop_poses[prop.name])
                jid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, f"{prop.name}/hinge")
                self.data.qpos[self.model.jnt_qposadr[jid]] = angle[frame]
                self.data.qvel[self.model.jnt_dofadr[jid]] = np.gradient(angle, FRAME_DT)[frame]

    def run(self, start_frames: list[int], nstep: int) -> list[Rollout]:
        """Batched replays of `nstep` physics steps from each start frame."""
        m, nq = self.model, self.nq
        init = np.stack([self.initial_state(k) for k in start_frames])
        ctrl = np.stack([self.controls(k, nstep) for k in start_frames])
        state, sensors = mujoco.rollout.rollout(m, self.data, init, ctrl)
        return [self._measure(k, nstep, state[b, :, 1 : 1 + nq], sensors[b]) for b, k in enumerate(start_frames)]

    def _measure(self, start_frame: int, nstep: int, qpos: np.ndarray, sensors: np.ndarray) -> Rollout:
        s, tr = self.settings, self.traj
        frac = self._frac(start_frame, nstep, offset=1.0)  # state after step i is at time (i + 1) dt
        base_ref = _interp(tr.qpos[:, :3], frac)
        quat_ref = _interp_quat(tr.qpos[:, 3:7], frac)
        angle = np.linalg.norm(quat_error(quat_ref, qpos[:, 3:7]), axis=-1)
        fallen = np.flatnonzero((base_ref[:, 2] - qpos[:, 2] > s.fall_height) | (angle > s.fall_angle))
        end = int(fallen[0]) if len(fallen) else nstep
        upto = slice(0, max(end, 1))
        joint_err = qpos[upto, 7:] - _interp(tr.qpos[:, 7:], frac)[upto]
        base_err = np.linalg.norm(qpos[upto, :3] - base_ref[upto], axis=-1)
        # Sensors are evaluated before each step integrates: sensordata[i] is the state at time i dt.
        feet = sensors[upto][:, self.foot_columns]
        feet_ref = _interp(tr.ee_pos[:, self.foot_ref], self._frac(start_frame, nstep))[upto]
        return Rollout(
            start=start_frame * FRAME_DT,
            duration=nstep * self.dt,
            fall_time=float((end + 1) * self.dt) if len(fallen) else None,
            joint_rms=float(np.sqrt(np.mean(joint_err**2))),
            base_error=float(base_err.max()),
            foot_error=float(np.linalg.norm(feet - feet_ref, axis=-1).max()),
        )

    def feedback(self) -> Rollout | None:
        """The whole motion under the optimizer's own feedback law, when the record has its gains.

        u = tau_ref - K_k (x (-) x_ref) (Crocoddyl's convention, Pinocchio state difference), with
        x_ref interpolated from the frames and K_k the gains of the solver node containing t, is the
        servos' feedforward: they apply u + kp (q_ref - q) + kd (qd_ref - qd) (`feedback_pd`, the
        default), or u alone (the servo target set at the measured state). None without
        `knots["gains"]`.
        """
        states = self.feedback_states()
        if states is None:
            return None
        qpos, sensors = states
        return self._measure(0, len(qpos), qpos, sensors)

    def feedback_references(self) -> dict[str, np.ndarray] | None:
        """Per physics step: the reference qpos (MuJoCo layout) and q, v (Pinocchio's), the
        reference torque and the solver node whose gains apply; and the gains. None without gains."""
        k = self.traj.knots
        if "gains" not in k or "dt" not in k or "time" not in k:
            return None
        tr = self.traj
        nstep = int(round(tr.duration / self.dt))
        frac = self._frac(0, nstep)
        qpos_ref = np.concatenate(
            [_interp(tr.qpos[:, :3], frac), _interp_quat(tr.qpos[:, 3:7], frac), _interp(tr.qpos[:, 7:], frac)], axis=1
        )
        running = np.flatnonzero(np.asarray(k["dt"]) > 0)
        starts = np.asarray(k["time"])[running]
        return {
            "qpos_ref": qpos_ref,
            "q_ref": qpos_mj_to_pin(qpos_ref),
            "v_ref": _interp(qvel_mj_to_pin(tr.qpos, tr.qvel), frac),
            "tau_ref": tr.joint_torque[np.clip(np.floor(frac + 1e-9).astype(int), 0, tr.num_frames - 1)],
            "node": running[np.clip(np.searchsorted(starts, frac * FRAME_DT + 1e-9, side="right") - 1, 0, None)],
            "gains": np.asarray(k["gains"], dtype=float),
        }

    def feedback_states(self, props: bool = False) -> tuple[np.ndarray, ...] | None:
        """The feedback replay's robot qpos and sensors after each physics step, until the fall;
        with `props`, also the rest of MuJoCo's qpos (the free props', e.g. a carried box)."""
        ref = self.feedback_references()
        if ref is None:
            return None
        tr, cfg, pm = self.traj, self.robot.config, self.robot.pin_model
        qpos_ref, q_ref, v_ref, tau_ref, node, gains = (
            ref[key] for key in ("qpos_ref", "q_ref", "v_ref", "tau_ref", "node", "gains")
        )
        nstep = len(qpos_ref)
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[: self.nq], d.qvel[: self.nv] = tr.qpos[0], tr.qvel[0]
        qpos = np.empty((nstep, self.nq))
        prop_qpos = np.empty((nstep, m.nq - self.nq)) if props else None
        sensors = np.empty((nstep, m.nsensordata))
        kp, kd = cfg.kp, cfg.kd
        if self.compiled:
            nstep = self._compiled_loop(ref, qpos, sensors, prop_qpos)
            return (qpos[:nstep], sensors[:nstep]) + ((prop_qpos[:nstep],) if props else ())
        # Without the compiled loop above: the law of the docstring, written for speed (it is most
        # of a walk's validation): views of MjData taken once, the state conversions (`qpos_mj_to_pin`,
        # `qvel_mj_to_pin`) inlined on preallocated arrays with the rotation in Python floats, the
        # state-independent products computed for all steps at once. Every operation is the one
        # the conversions do, in the same order, so the controls are bitwise those of the plain
        # form (tests/test_data_validate.py compares them).
        nq, nv = self.nq, self.nv
        qpos_now, qvel_now, ctrl, sensordata = d.qpos[:nq], d.qvel[:nv], d.ctrl, d.sensordata
        lin_now, rest_now, joints_vel = qvel_now[:3], qvel_now[3:], qvel_now[6:]
        q = np.empty(nq)
        dx = np.empty(2 * nv)
        dx_lin, dx_rest = dx[nv : nv + 3], dx[nv + 3 :]
        v_ref_lin, v_ref_rest = v_ref[:, :3], v_ref[:, 3:]
        pd = self.settings.feedback_pd
        kd_v_ref = kd * v_ref[:, 6:] if pd else None
        target_ref = qpos_ref[:, 7:]
        step = mujoco.mj_step
        difference = pin.difference
        losses = self._joint_losses
        for i in range(nstep):
            q[:3] = qpos_now[:3]
            q[3:6] = qpos_now[4:7]
            q[6] = qpos_now[3]
            q[7:] = qpos_now[7:]
            dx[:nv] = difference(pm, q_ref[i], q)
            w, x, y, z = qpos_now[3:7].tolist()
            a, b, c = lin_now.tolist()
            dx_lin[0] = (1 - 2 * (y * y + z * z)) * a + (2 * (x * y + w * z)) * b + (2 * (x * z - w * y)) * c
            dx_lin[1] = (2 * (x * y - w * z)) * a + (1 - 2 * (x * x + z * z)) * b + (2 * (y * z + w * x)) * c
            dx_lin[2] = (2 * (x * z + w * y)) * a + (2 * (y * z - w * x)) * b + (1 - 2 * (x * x + y * y)) * c
            dx_lin -= v_ref_lin[i]
            np.subtract(rest_now, v_ref_rest[i], out=dx_rest)
            u = tau_ref[i] - gains[node[i]] @ dx + losses(joints_vel)
            if pd:
                ctrl[:] = target_ref[i] + (u + kd_v_ref[i]) / kp
            else:
                ctrl[:] = qpos_now[7:] + (u + kd * joints_vel) / kp
            step(m, d)
            qpos[i] = qpos_now
            if props:
                prop_qpos[i] = d.qpos[nq:]
            sensors[i] = sensordata
            if i % 50 == 0 and self._fallen(qpos_ref[min(i + 1, nstep - 1)], qpos_now):
                nstep = i + 1
                break
        if props:
            return qpos[:nstep], sensors[:nstep], prop_qpos[:nstep]
        return qpos[:nstep], sensors[:nstep]

    def _compiled_loop(self, ref: dict[str, np.ndarray], qpos: np.ndarray, sensors: np.ndarray,
                       prop_qpos: np.ndarray | None) -> int:
        """The loop of `feedback_states` in C++ (trajopt/native/feedback_replay.hpp), from MjData's
        state into the given arrays; the steps taken. Its arrays are checked here: it reads them by
        address."""
        cfg, nu, pd = self.robot.config, self.nv - 6, self.settings.feedback_pd
        nstep = len(ref["qpos_ref"])
        arrays = {
            "qpos_ref": (ref["qpos_ref"], (nstep, self.nq)), "q_ref": (ref["q_ref"], (nstep, self.nq)),
            "v_ref": (ref["v_ref"], (nstep, self.nv)), "tau_ref": (ref["tau_ref"], (nstep, nu)),
            "node": (ref["node"], (nstep,)),
            "gains": (ref["gains"], (len(ref["gains"]), nu, 2 * self.nv)),
            "target_ref": (ref["qpos_ref"][:, 7:], (nstep, nu)),
            "kp": (cfg.kp, (nu,)), "kd": (cfg.kd, (nu,)), "damping": (self.damping, (nu,)),
            "frictionloss": (self.frictionloss, (nu,)), "qpos": (qpos, qpos.shape), "sensors": (sensors, sensors.shape),
        }
        if pd:
            arrays["kd_v_ref"] = (cfg.kd * ref["v_ref"][:, 6:], (nstep, nu))
        if prop_qpos is not None:
            arrays["props"] = (prop_qpos, prop_qpos.shape)
        if ref["node"].min() < 0 or ref["node"].max() >= len(ref["gains"]):
            raise ValueError("a physics step's solver node has no gains")
        keep, pointers = [], {}
        for key, (array, shape) in arrays.items():
            if key in ("qpos", "sensors", "props"):  # written in place
                a = array
                ok = a.flags.c_contiguous and a.flags.writeable and a.dtype == np.float64
            else:
                a = np.ascontiguousarray(array, dtype=np.int64 if key == "node" else np.float64)
                ok = True
            if not ok or a.shape != shape:
                raise ValueError(f"feedback replay: {key} must be a contiguous {shape} array, got {a.shape}")
            keep.append(a)  # alive until the call returns
            pointers[key] = a.ctypes.data
        return load_native().feedback_replay(
            self.model._address, self.data._address, self.robot.pin_model, pointers, nstep, pd,
            self.settings.joint_losses, self.settings.friction_smoothing, self.settings.fall_height,
            self.settings.fall_angle)

    @property
    def compiled(self) -> bool:
        """Whether the feedback replay runs in C++: the compiled module loads, and this replayer may use it."""
        return self.use_compiled and load_native() is not None

    def _fallen(self, qpos_ref: np.ndarray, qpos: np.ndarray) -> bool:
        s = self.settings
        angle = np.linalg.norm(quat_error(qpos_ref[3:7], qpos[3:7]))
        return bool(qpos_ref[2] - qpos[2] > s.fall_height or angle > s.fall_angle)

    def full(self, chunk: float = 1.0) -> Rollout:
        """The whole motion from its first frame, simulated in chunks until it falls."""
        m = self.model
        nstep, per = int(round(self.traj.duration / self.dt)), int(round(chunk / self.dt))
        ctrl = self.controls(0, nstep)
        state = self.initial_state(0)[None]
        qpos, sensors, done = [], [], 0
        while done < nstep:
            n = min(per, nstep - done)
            states, sens = mujoco.rollout.rollout(m, self.data, state, ctrl[None, done : done + n])
            qpos.append(states[0, :, 1 : 1 + self.nq])
            sensors.append(sens[0])
            state, done = states[:, -1], done + n
            if self._fallen(_interp(self.traj.qpos, self._frac(0, 1, offset=done))[0], qpos[-1][-1]):
                break
        return self._measure(0, done, np.concatenate(qpos), np.concatenate(sensors))

    def windows(self) -> list[Rollout]:
        """Windows of `settings.window` seconds from reference states, tiling the whole motion."""
        last = self.traj.num_frames - 1
        length = min(int(round(self.settings.window / FRAME_DT)), last)
        starts = list(range(0, last - length + 1, length))
        if starts[-1] + length < last:
            starts.append(last - length)
        return self.run(starts, int(round(length * FRAME_DT / self.dt)))
