"""From a solved problem to the trajectory record: 200 Hz frames, solver statistics and knots.

Knots (`traj.knots`, docs/data.md): the solver grid as Crocoddyl saw it, one row per node (running
and impulse; the terminal node only in `time` and `x`):

    time (K,)               s; an impulse node shares the time of the running node after it
    x (K, nq + nv)          states entering each node, Pinocchio layout (quaternion x, y, z, w;
                            base velocity in the body frame)
    u (K-1, nu)             joint torques (zeros at impulse nodes)
    dt (K-1,)               node duration (0 at impulse nodes)
    impulse (K-1,)          True at impulse (touchdown) nodes
    contact_force (K-1, nc, 6)  wrench on the robot at each contact point, world axes (impulse
                            nodes: the impulse in N s)
    gains (K-1, nu, 2 nv)   float32 feedback gains, only with `solver.keep_gains`:
                            u = u[k] - gains[k] @ diff(x[k], x_measured)
"""

from __future__ import annotations

import numpy as np

from opt2skill.data.record import Trajectory, build_trajectory
from opt2skill.model.convert import qpos_pin_to_mj, qvel_pin_to_mj
from opt2skill.model.robot import Robot
from opt2skill.scene.description import Scene
from opt2skill.trajopt.frames import Frames, contact_wrenches
from opt2skill.trajopt.phases import Problem
from opt2skill.trajopt.solver import Solution


def knots(problem: Problem, solution: Solution, keep_gains: bool) -> dict[str, np.ndarray]:
    shooting = problem.shooting
    running = problem.nodes[:-1]
    n, nc = len(running), len(problem.contact_names)
    u = np.zeros((n, problem.nu))
    force = np.zeros((n, nc, 6))
    for k, (node, model, data) in enumerate(zip(running, shooting.runningModels, shooting.runningDatas)):
        if node.kind == "running":
            u[k] = solution.us[k]
        model.calc(data, solution.xs[k], solution.us[k])  # just before the read: nodes may share a scratch
        contact_wrenches(data, problem, node.contacts, force[k])
    out = {
        "time": np.array([node.time for node in problem.nodes]),
        "x": np.array(solution.xs),
        "u": u,
        "dt": np.array([node.dt for node in running]),
        "impulse": np.array([node.kind == "impulse" for node in running]),
        "contact_force": force,
    }
    if keep_gains:
        ndx = 2 * shooting.runningModels[0].state.nv
        gains = np.zeros((n, problem.nu, ndx), dtype=np.float32)
        for k, node in enumerate(running):
            if node.kind == "running":
                gains[k] = solution.K[k]
        out["gains"] = gains
    return out


def to_trajectory(
    robot: Robot,
    frames: Frames,
    problem: Problem,
    *,
    task: str,
    params: dict[str, float],
    seed: int,
    solver: dict,
    provenance: dict,
    knots: dict[str, np.ndarray],
    scene: Scene | None = None,
) -> Trajectory:
    qpos = qpos_pin_to_mj(frames.q)
    qvel = qvel_pin_to_mj(qpos, frames.v)
    return build_trajectory(
        robot,
        qpos,
        qvel,
        frames.tau,
        frames.wrench,
        frames.active,
        task=task,
        contact_names=problem.contact_names,
        params=params,
        seed=seed,
        solver=solver,
        provenance=provenance,
        knots=knots,
        scene=scene,
        prop_poses=frames.prop_poses,
    )
