"""The squat: a real Crocoddyl solve end to end, the record's conventions, gains and reproducibility."""

import numpy as np
import pinocchio as pin
import pytest

from opt2skill.data.checks import frame_dynamics_residual, touchdown_frames
from opt2skill.data.record import FRAME_DT
from opt2skill.model import load_robot
from opt2skill.tasks import get_task
from opt2skill.trajopt.solver import riccati_gains


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


@pytest.fixture(scope="module")
def squat(robot):
    task = get_task("squat", robot, {"solver.keep_gains": True})
    return task, task.solve({"depth": 0.12}, seed=3)


def test_squat_record_is_complete_and_goes_down_and_back(robot, squat):
    task, traj = squat
    assert traj.task == "squat" and traj.seed == 3 and traj.params == {"depth": 0.12}
    assert np.allclose(np.diff(traj.time), FRAME_DT) and traj.num_frames == int(round(1.6 / FRAME_DT)) + 1
    assert traj.contact_names == ("left_foot", "right_foot") and traj.contact_active.all()
    errors = task.task_errors(traj)
    assert errors["depth_error"]["value"] < errors["depth_error"]["limit"]
    assert errors["end_error"]["value"] < errors["end_error"]["limit"]
    assert traj.com[:, 2].min() < traj.com[0, 2] - 0.1
    for key in ("name", "iterations", "converged", "cost", "dynamic_gap", "solve_time"):
        assert key in traj.solver
    assert traj.solver["converged"] and traj.solver["dynamic_gap"] < 1e-8
    assert traj.provenance["robot_hash"] == robot.hash and "task_config" in traj.provenance


def test_squat_frames_satisfy_the_equations_of_motion(robot, squat):
    _, traj = squat
    residual = frame_dynamics_residual(robot, traj)
    smooth = ~touchdown_frames(traj.contact_active)
    assert np.abs(residual[smooth]).max() < 1e-6


def test_wrenches_are_on_the_robot_at_the_soles_in_world_axes(robot, squat):
    """Standing still at the start: the normal forces carry the weight, the CoPs are inside the soles."""
    _, traj = squat
    weight = 9.81 * sum(inertia.mass for inertia in robot.pin_model.inertias)
    first = traj.contact_wrench[0]
    assert first[:, 2].sum() == pytest.approx(weight, rel=0.01)
    assert np.abs(first[:, :2]).max() < 0.02 * weight
    foot = robot.config.feet[0]
    for force in traj.contact_wrench.reshape(-1, 6):
        cop_x, cop_y = -force[4] / force[2], force[3] / force[2]
        assert abs(cop_x) <= foot.half_length and abs(cop_y) <= foot.half_width


def test_gains_follow_the_documented_convention(robot, squat):
    """u = u[k] - gains[k] @ diff(x[k], x): with it a perturbed start returns to the plan, open loop it does not."""
    task, traj = squat
    knots = traj.knots
    assert knots["gains"].dtype == np.float32
    assert knots["gains"].shape == (len(knots["u"]), robot.nu, 2 * robot.nv)
    problem = task.builder.build(task.plan(traj.params).phases, knots["x"][0], task.config.solver.dt)
    # open loop, the documented sign, the opposite sign
    deviation = {sign: _pushed_deviation(robot, problem, knots, sign * knots["gains"]) for sign in (0.0, 1.0, -1.0)}
    assert deviation[1.0] < 1e-2
    for other in (0.0, -1.0):
        assert not np.isfinite(deviation[other]) or deviation[other] > 0.1


def _pushed_deviation(robot, problem, knots, gains) -> float:
    """How far from the plan's last state a forward push of the base at the start ends under
    u = u[k] - gains[k] @ diff(x[k], x) on the optimizer's own dynamics."""
    state = problem.shooting.runningModels[0].state
    x = knots["x"][0].copy()
    x[robot.pin_model.nq + 0] += 0.15
    for k, (model, data) in enumerate(zip(problem.shooting.runningModels, problem.shooting.runningDatas)):
        model.calc(data, x, knots["u"][k] - gains[k] @ state.diff(knots["x"][k], x))
        x = data.xnext.copy()
    return float(np.linalg.norm(state.diff(knots["x"][-1], x)))


def test_the_same_parameters_give_the_same_trajectory(robot, squat):
    task, traj = squat
    again = get_task("squat", robot, {"solver.keep_gains": True}).solve({"depth": 0.12}, seed=3)
    assert np.array_equal(again.qpos, traj.qpos) and np.array_equal(again.joint_torque, traj.joint_torque)
    assert np.array_equal(again.knots["gains"], traj.knots["gains"])


def test_interpolated_frames_are_measurably_less_consistent(robot):
    """The alternative completion keeps the knots' torques: its frames leave a dynamics residual."""
    traj = get_task("squat", robot, {"solver.completion": "interpolate"}).solve({"depth": 0.12}, seed=0)
    residual = np.abs(frame_dynamics_residual(robot, traj)).max()
    assert 1e-3 < residual < 5.0


def test_knots_hold_the_solver_grid(robot, squat):
    _, traj = squat
    k = traj.knots
    assert k["x"].shape == (len(k["time"]), robot.pin_model.nq + robot.nv)
    assert np.allclose(np.diff(k["time"]), k["dt"]) and not k["impulse"].any()
    q_pin = pin.neutral(robot.pin_model)
    assert k["x"].shape[1] == len(q_pin) + robot.nv


def test_riccati_gains_repeat_the_solvers_and_soften_with_regularization(robot, squat):
    """One backward pass at the converged squat gives the solver's own gains back (the squat is one
    full-horizon solve; the solver's were computed one iterate earlier, measured 1.7 % apart); regularizing Quu and Vxx lowers every node's gain, and those softer gains
    still bring a pushed start back to the plan."""
    task, traj = squat
    k = traj.knots
    plan = task.plan(traj.params)
    solver = task.config.solver
    problem = task.builder.build(task._with_standard_costs(plan), k["x"][0], solver.dt, integrator=solver.integrator)
    us = [np.asarray(u) for u in k["u"]]
    stiff = np.array(riccati_gains(problem.shooting, k["x"], us, solver.reg_init))
    assert np.linalg.norm(stiff - k["gains"]) < 0.05 * np.linalg.norm(k["gains"])
    soft = np.array(riccati_gains(problem.shooting, k["x"], us, 1e-2))
    ratio = np.linalg.norm(soft, axis=(1, 2)) / np.linalg.norm(stiff, axis=(1, 2))
    assert ratio.max() < 0.2 and ratio.min() > 1e-3  # measured 0.014 to 0.079
    assert _pushed_deviation(robot, problem, k, soft) < 1e-2
    again = get_task("squat", robot, {"solver.keep_gains": True, "solver.gains": "riccati",
                                      "solver.gains_regularization": 1e-2}).solve(traj.params, seed=3)
    assert np.linalg.norm(again.knots["gains"] - soft) < 1e-5 * np.linalg.norm(soft)  # float32 in the record
    assert np.array_equal(again.qpos, traj.qpos)  # only the gains change
