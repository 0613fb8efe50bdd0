"""References recorded from the simulator itself: a motion the physics can track exactly.

A recorded reference is what the environment would see when replaying the same PD targets: a reset
at the start state with the servos holding it, then one target vector per policy step. Frame k is
the state after k steps; its torques and contact wrenches are the means over step k (the frame's
held values, as in the record). Tests use it to check the reward alignment; the benchmark uses it
when no dataset is given.
"""

from __future__ import annotations

import numpy as np

from opt2skill.data.record import FRAME_DT, Trajectory, build_trajectory
from opt2skill.model.robot import Robot
from opt2skill.model.standing import feedforward_ctrl
from opt2skill.model.statics import gravity_compensation
from opt2skill.sim import MujocoBatchedSim, SimConfig


def squat_targets(robot: Robot, steps: int, depth: float = 0.15, period: float = 0.6) -> np.ndarray:
    """PD targets (steps, nu) of a gentle squat: the gravity-compensated stand with hips, knees and
    ankles bent by depth * sin^2(2 pi t / period) (a squat every period / 2)."""
    stand = feedforward_ctrl(robot, robot.stand_qpos, gravity_compensation(robot, robot.stand_qpos).torque)
    names = robot.config.joint_names
    bend = np.zeros(robot.nu)
    for side in ("left", "right"):
        bend[names.index(f"{side}_hip_pitch")] = 0.5
        bend[names.index(f"{side}_knee")] = -1.0
        bend[names.index(f"{side}_ankle_pitch")] = 0.5
    t = np.arange(steps) * FRAME_DT
    return stand + depth * np.sin(2 * np.pi * t / period)[:, None] ** 2 * bend


def record_reference(robot: Robot, targets: np.ndarray, task: str = "recorded") -> Trajectory:
    """The record of the robot started at its stand pose and driven by `targets` (steps, nu)."""
    q0, v0 = robot.stand_qpos[None], np.zeros((1, robot.nv))
    with MujocoBatchedSim(robot, 1, SimConfig(nsubstep=5, nthread=1)) as sim:
        start = sim.reset(np.array([0]), q0, v0, targets=q0[:, 7:])
        outs = [sim.step(t[None]) for t in targets]
    last = outs[-1]
    qpos = np.concatenate([start.qpos] + [o.qpos for o in outs])
    qvel = np.concatenate([start.qvel] + [o.qvel for o in outs])
    torque = np.concatenate([o.torque_mean for o in outs] + [last.torque_mean])
    wrench = np.concatenate([o.contact_wrench_mean for o in outs] + [last.contact_wrench_mean])
    active = np.concatenate([o.contact_found > 0 for o in outs] + [last.contact_found > 0])
    feet = tuple(f.name for f in robot.config.feet)
    return build_trajectory(robot, qpos, qvel, torque, wrench, active, task=task, contact_names=feet,
                            params={}, seed=0)
