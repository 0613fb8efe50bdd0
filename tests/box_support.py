"""Shared by the box tasks' tests: the balance of the robot's and the held box's momentum."""

import numpy as np
import pinocchio as pin

from opt2skill.model.convert import qpos_mj_to_pin, qvel_mj_to_pin
from opt2skill.trajopt.skills.box_handling import HANDS


def momentum_rate_residual(robot, traj, box_mass: float):
    """Per frame: d/dt of the robot's linear momentum minus (all contact forces + weight), and for the
    box the sum of the hands' forces on it minus its own momentum rate minus its weight."""
    pm = robot.pin_model
    pd = pm.createData()
    q = qpos_mj_to_pin(traj.qpos)
    v = qvel_mj_to_pin(traj.qpos, traj.qvel)
    mass = pin.computeTotalMass(pm)
    g = np.array([0.0, 0.0, -9.81])
    hands = [list(traj.contact_names).index(h) for h in HANDS]
    hand_frames = [robot.pin_frame_id(robot.config.end_effectors[h]) for h in HANDS]
    robot_res, box_res = [], []
    for k in range(len(q) - 1):
        a = (v[k + 1] - v[k]) / 0.005
        pin.centerOfMass(pm, pd, q[k], v[k], a)
        forces = traj.contact_wrench[k, :, :3].sum(axis=0)
        robot_res.append(mass * pd.acom[0] - forces - mass * g)
        if traj.contact_active[k, hands].all():
            # the box moves rigidly with the hands: its acceleration is their contact points' mean
            pin.forwardKinematics(pm, pd, q[k], v[k], a)
            pin.updateFramePlacements(pm, pd)
            a_box = np.mean([pin.getFrameClassicalAcceleration(pm, pd, fid, pin.LOCAL_WORLD_ALIGNED).linear
                             for fid in hand_frames], axis=0)
            on_box = -traj.contact_wrench[k, hands, :3].sum(axis=0)
            box_res.append(on_box + box_mass * g - box_mass * a_box)
    return np.array(robot_res), np.array(box_res)


def carried_frames(task, traj) -> np.ndarray:
    """Frames whose step lies in a phase that carries the box (from the task's own plan)."""
    t, out = 0.0, np.zeros(traj.num_frames - 1, dtype=bool)
    for phase in task.plan(traj.params).phases:
        if phase.payload:
            out[int(round(t / 0.005)) : int(round((t + phase.duration) / 0.005))] = True
        t += phase.duration
    return out
