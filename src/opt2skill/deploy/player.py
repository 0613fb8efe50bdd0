"""The standalone sim-to-sim player: an exported policy (ONNX + its metadata) driving one simulated
Digit as a robot-side program would, at 200 Hz with PD servos at 2 kHz.

It uses only the ONNX file and its metadata, onnxruntime, MuJoCo, the robot model (for the MJCF
and its sensors) and the dataset reader; nothing of the training code (`envs`, `rl`, `sim`). Its
own single-world loop (`mj_step` at `physics_dt`, 0.5 ms by default) reads the sensors the robot
has (IMU orientation, gyro and velocimeter, joint encoders), adds optional Gaussian sensor noise,
builds the observation from the metadata's layout with its own histories, runs the network, and
applies the PD targets after an optional extra latency. The servos use the metadata's gains and
torque limits, not the model's. A judge with the ground truth (not the robot) applies the training
task's terminations and records what happened, so `eval.metrics` measures it like `opt2skill eval`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from opt2skill.data.record import Trajectory, build_trajectory
from opt2skill.deploy.metadata import INPUT, PolicyMetadata, read_metadata
from opt2skill.deploy.observations import ActorObservation, Readings, ReferenceFrames
from opt2skill.errors import ConfigError, DataError
from opt2skill.geometry import projected_gravity, quat_error
from opt2skill.model import load_robot
from opt2skill.model.robot import Robot
from opt2skill.model.sensors import SensorLayout, contact_wrenches
from opt2skill.scene.build import build_model, prop_hinge, prop_qpos
from opt2skill.scene.props import Door
from opt2skill.scene.description import Scene

MAX_SPEED = 100.0  # any |qvel| beyond this (m/s, rad/s): the simulation diverged


@dataclass(frozen=True)
class PlayerConfig:
    physics_dt: float = 0.0005  # s: 2 kHz PD, as on the robot (training: 1 kHz)
    latency: float = 0.0  # s, extra delay between reading the sensors and applying the targets
    noise: float = 0.0  # factor on the training's sensor-noise standard deviations (Table II)
    seed: int = 0

    def check(self, policy_dt: float) -> int:
        """Physics steps per policy step."""
        if not 1e-5 <= self.physics_dt <= policy_dt:
            raise ConfigError(f"physics dt must be in [1e-5, {policy_dt}] s, got {self.physics_dt}")
        substeps = round(policy_dt / self.physics_dt)
        if abs(substeps * self.physics_dt - policy_dt) > 1e-9:
            raise ConfigError(f"physics dt {self.physics_dt} s must divide the policy period {policy_dt} s")
        if not 0.0 <= self.latency <= 0.1:
            raise ConfigError(f"latency must be in [0, 0.1] s, got {self.latency}")
        if self.noise < 0:
            raise ConfigError(f"noise factor must be >= 0, got {self.noise}")
        return substeps


@dataclass
class PlayerRollout:
    reference: Trajectory
    tracked: Trajectory
    cause: str  # "time_out" (the reference ended) or the termination (fall, height_error, ...)
    observations: np.ndarray | None = None  # (steps, obs_dim) what the policy saw, when asked for

    @property
    def fell(self) -> bool:
        return self.cause != "time_out"


class Player:
    def __init__(self, onnx_path: str | Path, config: PlayerConfig = PlayerConfig(), robot: Robot | None = None):
        import onnxruntime as ort

        self.path = Path(onnx_path)
        self.meta: PolicyMetadata = read_metadata(self.path)
        meta = self.meta
        self.robot = robot or load_robot(meta.robot["name"])
        if self.robot.hash != meta.robot["hash"]:
            raise DataError(f"{self.path} was trained on a different '{meta.robot['name']}' robot file "
                            f"(hash {meta.robot['hash'][:12]}); the installed one has {self.robot.hash[:12]}")
        if self.robot.config.joint_names != meta.joint_names:
            raise DataError(f"{self.path}: the policy's joint order differs from robot '{self.robot.name}'")
        self.config = config
        self.policy_dt = float(meta.control["policy_dt"])
        self.substeps = config.check(self.policy_dt)
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        self.session = ort.InferenceSession(str(self.path), options, providers=["CPUExecutionProvider"])
        self._check_network()
        self.kp, self.kd, self.limit = meta.array("kp"), meta.array("kd"), meta.array("torque_limit")
        self.scene: Scene | None = None
        self._use_scene(Scene())
        self.contacts = meta.contacts  # the references' contacts the policy reads forces at
        self._contact_rows = self.sensors.contact_rows(self.contacts)
        self.default_pose = meta.array("default_pose")
        self.scale, self.clip = float(meta.control["action_scale"]), float(meta.control["action_clip"])
        self.sigma = {k: config.noise * float(v) for k, v in meta.observation["noise_std"].items()}
        self.observation = ActorObservation(meta)
        self.terminations = meta.task["terminations"]
        self.rng = np.random.default_rng(config.seed)

    def _check_network(self) -> None:
        """One evaluation before any playback: the network must map the metadata's observation to one
        action per joint (a file's declared shapes can leave sizes open)."""
        try:
            outputs = self.session.run(None, {INPUT: np.zeros((1, self.meta.obs_dim), np.float32)})
        except Exception as exc:  # onnxruntime raises its own kinds on a shape mismatch
            raise DataError(f"{self.path}: the network does not run on the {self.meta.obs_dim} observations its "
                            f"metadata describes ({type(exc).__name__})") from None
        shape = tuple(np.shape(outputs[0]))
        if len(outputs) != 1 or shape != (1, self.meta.nu):
            raise DataError(f"{self.path}: the network outputs shape {shape} for one observation; its metadata "
                            f"describes {self.meta.nu} actions (one per joint)")

    def _use_scene(self, scene: Scene) -> None:
        """The physics of `scene` (a reference's terrain and props, the robot's state first), built
        when it differs from the current one."""
        if scene == self.scene:
            return
        self.model = build_model(self.robot, scene)
        self.model.opt.timestep = self.config.physics_dt
        self._set_servos()
        self.data = mujoco.MjData(self.model)
        self.sensors = SensorLayout.from_model(self.model, self.robot.config)
        self.scene = scene

    def _set_servos(self) -> None:
        """The servos of the metadata: u = clip(kp (target - q) - kd qd, +-limit) at every physics step."""
        m = self.model
        m.actuator_gainprm[:, 0] = self.kp
        m.actuator_biasprm[:, :3] = np.stack([np.zeros_like(self.kp), -self.kp, -self.kd], axis=1)
        m.actuator_forcerange[:] = np.stack([-self.limit, self.limit], axis=1)

    # ------------------------------------------------------------ robot side

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.session.run(None, {INPUT: obs[None].astype(np.float32)})[0][0].astype(float)

    def sense(self, noisy: bool = True) -> Readings:
        """Sensor readings at the current state (MuJoCo's sensors after mj_forward)."""
        s, sd = self.sensors, self.data.sensordata
        r = Readings(gravity=projected_gravity(s.take(sd, "imu_quat")), base_lin_vel=s.take(sd, "imu_linvel").copy(),
                     base_ang_vel=s.take(sd, "imu_gyro").copy(), joint_pos=s.take(sd, "joint_pos").copy(),
                     joint_vel=s.take(sd, "joint_vel").copy())
        if noisy and self.config.noise > 0:
            for name, key in (("gravity", "gravity"), ("base_lin_vel", "base_lin_vel"), ("base_ang_vel", "base_ang_vel"),
                              ("joint_pos", "joint_pos"), ("joint_vel", "joint_vel")):
                value = getattr(r, name)
                setattr(r, name, value + self.sigma[key] * self.rng.standard_normal(value.shape))
        return r

    # ------------------------------------------------------------ one reference

    def run(self, reference: Trajectory, keep_observations: bool = False) -> PlayerRollout:
        """Track `reference` from its first frame until it ends or a termination."""
        nq, nv = self.robot.nq, self.robot.nv  # the robot's part of the scene's state
        if reference.qpos.shape[1] != nq:
            raise DataError(f"the reference has {reference.qpos.shape[1]} positions; robot '{self.robot.name}' has {nq}")
        self._use_scene(reference.scene)
        m, d = self.model, self.data
        ref = ReferenceFrames(reference, self.contacts)
        mujoco.mj_resetData(m, d)  # props at their scene poses
        d.qpos[:nq], d.qvel[:nv] = reference.qpos[0], reference.qvel[0]
        boxes = {p.name: prop_qpos(m, p.name) for p in reference.scene.props if p.free}
        for name, at in boxes.items():  # ... or where the reference has them at its first frame
            if name in reference.prop_poses:
                d.qpos[at] = reference.prop_poses[name][0]
        d.ctrl[:] = reference.qpos[0, 7:]  # the servos hold the start pose
        mujoco.mj_forward(m, d)
        r = self.sense()
        clean_q = self.sensors.take(d.sensordata, "joint_pos")
        slots = clean_q + self.sigma["joint_pos"] * self.rng.standard_normal((self.observation.depth, m.nu))
        self.observation.reset(slots, (reference.qpos[0, 7:] - self.default_pose) / self.scale)

        delay = int(round(self.config.latency / self.config.physics_dt))
        pending: deque[tuple[int, np.ndarray]] = deque()
        readings = np.empty((self.substeps, m.nsensordata))  # each physics step's sensors, decoded per policy step
        qpos, qvel, torque, wrench, active, seen = [d.qpos[:nq].copy()], [d.qvel[:nv].copy()], [], [], [], []
        doors = {p.name: (p, prop_hinge(m, p.name)) for p in reference.scene.props if isinstance(p, Door)}

        def prop_poses_now() -> dict[str, np.ndarray]:  # boxes' poses, doors' hinge frames
            return {**{name: d.qpos[at].copy() for name, at in boxes.items()},
                    **{name: door.pose(d.qpos[at]) for name, (door, at) in doors.items()}}

        props = {name: [pose] for name, pose in prop_poses_now().items()}
        substep, cause, action = 0, "time_out", None
        for t in range(reference.num_frames - 1):
            if action is not None:
                self.observation.push(r.joint_pos, action)
            obs = self.observation.observe(r, ref, t)
            if keep_observations:
                seen.append(obs)
            action = np.clip(self.act(obs), -self.clip, self.clip)
            pending.append((substep + delay, self.default_pose + self.scale * action))
            for k in range(self.substeps):
                while pending and pending[0][0] <= substep:
                    d.ctrl[:] = pending.popleft()[1]
                mujoco.mj_step(m, d)  # sensors of this step: its start state and the forces acting during it
                substep += 1
                readings[k] = d.sensordata
            mujoco.mj_forward(m, d)  # sensors at the end of the step, where the policy reads them
            if not (np.all(np.isfinite(d.qpos)) and np.all(np.abs(d.qvel) < MAX_SPEED)) or d.warning[
                    mujoco.mjtWarning.mjWARN_BADQACC].number:
                cause = "unstable"
                break
            qpos.append(d.qpos[:nq].copy())
            qvel.append(d.qvel[:nv].copy())
            for name, pose in prop_poses_now().items():
                props[name].append(pose)
            torque.append(self.sensors.take(readings, "joint_torque").mean(axis=0))  # MEAN over the step
            wrench.append(self._wrenches(readings).mean(axis=0))
            active.append(self._found(readings[-1]) > 0)  # LAST
            ended = self._judge(d.qpos[:nq], reference.qpos[t + 1])
            if ended:
                cause = ended
                break
            r = self.sense()
        if not torque:  # diverged in the first step: nothing to compare
            raise DataError(f"the simulation diverged in the first policy step of reference {reference.params}")
        for series in (torque, wrench, active):
            series.append(series[-1])  # the last frame repeats the last step's torques and forces (as the record)
        tracked = build_trajectory(self.robot, np.array(qpos), np.array(qvel), np.array(torque), np.array(wrench),
                                   np.array(active), task=reference.task, contact_names=tuple(self.contacts),
                                   params=reference.params, seed=reference.seed, ee_names=reference.ee_names,
                                   scene=reference.scene, prop_poses={k: np.array(v) for k, v in props.items()})
        return PlayerRollout(reference, tracked, cause, np.array(seen) if keep_observations else None)

    def _wrenches(self, sensordata: np.ndarray) -> np.ndarray:
        """Wrench on each of the policy's contacts (..., ncontacts, 6), world axes: a foot's about its
        sole site, a point contact's (hand, elbow) force with a zero torque."""
        s = self.sensors
        feet = s.contact_wrench(sensordata, s.take(sensordata, "sole_pos"))
        return contact_wrenches(feet, s.point_force(sensordata), self._contact_rows)

    def _found(self, sensordata: np.ndarray) -> np.ndarray:
        """Contact points of each of the policy's contacts (ncontacts,)."""
        s = self.sensors
        return np.concatenate([s.contact_found(sensordata), s.point_found(sensordata)])[self._contact_rows]

    def _judge(self, qpos: np.ndarray, ref_qpos: np.ndarray) -> str | None:
        """The training task's fall, height and orientation terminations on the true state (0 switches
        one off); flat ground."""
        t = self.terminations
        cause = None
        if t.get("min_height") and qpos[2] < t["min_height"]:
            cause = "fall"
        if t.get("max_height_error") and abs(qpos[2] - ref_qpos[2]) > t["max_height_error"]:
            cause = "height_error"
        if t.get("max_orientation_error") and np.linalg.norm(quat_error(ref_qpos[3:7], qpos[3:7])) > t["max_orientation_error"]:
            cause = "orientation_error"
        return cause  # drifting from the reference ends nothing: E_pos measures it (as `opt2skill eval`)
