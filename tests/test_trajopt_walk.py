"""A short real walk (4 steps): dynamics, limits, contacts, standing start and end, task checks."""

import dataclasses

import numpy as np
import pytest

from opt2skill.data.checks import frame_dynamics_residual, site_poses, touchdown_frames
from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.tasks import get_task
from opt2skill.trajopt.solver import solve_shooting

PARAMS = dict(speed=0.6, clearance=0.12, step_duration=0.36, double_support=0.2, lateral_speed=0.0,
              yaw_rate=0.0, height_offset=-0.02)


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


@pytest.fixture(scope="module")
def walk(robot):
    task = get_task("walk", robot, {"steps": 4, "duration": 3.0})
    return task, task.solve(PARAMS, seed=11)


def test_walk_frames_satisfy_the_equations_of_motion(robot, walk):
    _, traj = walk
    residual = np.abs(frame_dynamics_residual(robot, traj)).max(axis=1)
    impacts = touchdown_frames(traj.contact_active)
    assert impacts.sum() == 4  # one touchdown per step
    assert residual[~impacts].max() < 1e-6
    assert traj.solver["dynamic_gap"] < 1e-6


def test_frames_follow_the_plan_at_the_knots(walk):
    """The default frames ("track" on the "matched" plan) pass through the solver's knots: joints
    within a few hundredths of a radian (Euler plans with feedback-law frames left 0.06 to 0.13 rad)."""
    _, traj = walk
    k = traj.knots
    running = np.r_[np.asarray(k["dt"]) > 0, True]
    frames = np.round(np.asarray(k["time"])[running] / 0.005).astype(int)
    x = np.asarray(k["x"])[running]
    assert np.abs(traj.qpos[frames, 7:] - x[:, 7:27]).max() < 0.02
    assert np.linalg.norm(traj.qpos[frames, :3] - x[:, :3], axis=1).max() < 0.005
    assert np.abs(traj.qvel[frames, 6:] - x[:, 27 + 6 :]).max() < 0.5


def test_walk_respects_torque_and_joint_limits(robot, walk):
    _, traj = walk
    assert np.all(np.abs(traj.joint_torque) <= robot.config.torque_limit + 1e-9)
    pm = robot.pin_model
    q = traj.qpos[:, 7:]
    assert np.all(q >= pm.lowerPositionLimit[7:]) and np.all(q <= pm.upperPositionLimit[7:])


def test_contact_wrenches_stay_in_friction_cones_and_soles(robot, walk):
    _, traj = walk
    mu = robot.config.friction_coefficient
    f = traj.contact_wrench[traj.contact_active]
    assert f[:, 2].min() >= 0.0
    assert np.all(np.linalg.norm(f[:, :2], axis=1) <= mu * f[:, 2] + 1e-6)
    loaded = f[f[:, 2] > 20.0]
    foot = robot.config.feet[0]
    # Soles stay flat and face forward (no yaw here), so world axes are sole axes.
    assert np.all(np.abs(loaded[:, 4]) <= foot.half_length * loaded[:, 2] + 1e-6)
    assert np.all(np.abs(loaded[:, 3]) <= foot.half_width * loaded[:, 2] + 1e-6)
    assert np.abs(traj.contact_wrench[~traj.contact_active]).max() == 0.0


def test_stance_feet_do_not_slip(robot, walk):
    _, traj = walk
    for c, name in enumerate(traj.contact_names):
        foot = next(f for f in robot.config.feet if f.sole_site == robot.config.end_effectors[name])
        pos, _ = site_poses(robot, traj.qpos, [foot.sole_site, *foot.corner_sites])
        active = traj.contact_active[:, c].astype(np.int8)
        starts = np.flatnonzero(np.diff(np.concatenate([[0], active])) == 1)
        stops = np.flatnonzero(np.diff(np.concatenate([active, [0]])) == -1) + 1
        assert len(starts) >= 2  # it stepped
        for a, b in zip(starts, stops):
            assert np.linalg.norm(pos[a:b] - pos[a], axis=-1).max() < 2e-3


def test_walk_starts_and_ends_standing_and_steps_in_between(walk):
    _, traj = walk
    assert traj.contact_active[0].all() and traj.contact_active[-1].all()
    assert np.abs(traj.qvel[0]).max() == 0.0 and np.abs(traj.qvel[-1]).max() < 0.05
    single = traj.contact_active.sum(axis=1) == 1
    assert traj.contact_active[single, 0].any() and traj.contact_active[single, 1].any()
    assert traj.qpos[-1, 0] - traj.qpos[0, 0] > 0.3  # it went forward


def test_walk_meets_its_requested_speed_and_clearance(walk):
    task, traj = walk
    errors = task.task_errors(traj)
    assert set(errors) == {"speed_error", "clearance_error"}
    for error in errors.values():
        assert 0.0 <= error["value"] < error["limit"]


def test_windows_stopped_with_gaps_are_committed_feasible(robot):
    """One iteration per window leaves gaps; each such window is replaced by its feedback rollout."""
    task = get_task("walk", robot, {"steps": 4, "duration": 3.0, "receding.max_iter": 1, "receding.first_max_iter": 1})
    traj = task.solve(PARAMS, seed=11)
    assert "closed by rollout" in traj.solver["stop_reason"]
    assert traj.solver["dynamic_gap"] < 1e-9
    residual = np.abs(frame_dynamics_residual(robot, traj)).max(axis=1)
    assert residual[~touchdown_frames(traj.contact_active)].max() < 1e-6


@pytest.mark.parametrize("threshold", [0.01, 0.2])
def test_short_steps_raise_the_regularization_below_the_setting(robot, threshold):
    """`solver.reg_increase_below` is Crocoddyl's own rule: after an iteration whose step is no
    longer than it the regularization rises tenfold; after a full step it falls tenfold; between,
    it stays (docs/trajopt.md, "Speed: the solver's own levers")."""
    task = get_task("walk", robot, {"steps": 2, "duration": 1.5, "solver.reg_increase_below": threshold})
    plan = task.plan(PARAMS)
    problem = task.builder.build(task._with_standard_costs(plan), plan.x0, 0.03, integrator="matched")
    settings = dataclasses.replace(task.config.solver, stall_tol=0.0)
    sol = solve_shooting(problem.shooting, settings, max_iter=25)
    regs = [settings.reg_init] + sol.regularization
    seen = set()
    for step, before, after in zip(sol.steps, regs, regs[1:]):
        if step <= threshold:
            expected, seen = min(10 * before, 1e9), seen | {"raised"}
        elif step > 0.5:
            expected, seen = max(before / 10, 1e-9), seen | {"lowered"}
        else:
            expected, seen = before, seen | {"kept"}
        assert after == pytest.approx(expected, rel=1e-9), (step, before, after)
    # steps between the two settings occur (raised with 0.2, kept with 0.01), and both changes do
    assert any(0.2 >= step > 0.01 for step in sol.steps)
    assert {"raised", "lowered"} <= seen


def test_a_stricter_acceptance_takes_shorter_steps(robot):
    """`solver.accept_step` is Crocoddyl's th_acceptStep: the same solve with a stricter share of the
    predicted decrease follows the default until an iteration whose longer trial steps fall short of
    it, and there takes a shorter step (the line search tries 1, 1/2, ... in order)."""
    task = get_task("walk", robot, {"steps": 2, "duration": 1.5})
    plan = task.plan(PARAMS)
    problem = task.builder.build(task._with_standard_costs(plan), plan.x0, 0.03, integrator="matched")
    steps = {}
    for accept in (0.1, 0.9):
        settings = dataclasses.replace(task.config.solver, stall_tol=0.0, accept_step=accept)
        steps[accept] = solve_shooting(problem.shooting, settings, max_iter=25).steps
    first = next(i for i, (default, strict) in enumerate(zip(steps[0.1], steps[0.9])) if default != strict)
    assert steps[0.9][first] < steps[0.1][first], (first, steps)


def test_a_window_ends_when_a_full_step_leaves_its_committed_part_in_place(robot):
    """`solver.commit_tol`: the solve follows the default one iteration for iteration, and ends at the
    first full step after which no committed state moved by more than the tolerance; without the
    setting the same solve goes on to its cap (docs/trajopt.md, "Speed: stopping on the committed part")."""
    task = get_task("walk", robot, {"steps": 2, "duration": 1.5})
    plan = task.plan(PARAMS)
    problem = task.builder.build(task._with_standard_costs(plan), plan.x0, 0.03, integrator="matched")
    assert task.config.solver.commit_tol == 0.01  # the walk's default since 2026-12-07
    assert task.config.solver.reg_increase_below == 0.1  # likewise
    free = dataclasses.replace(task.config.solver, stall_tol=0.0, commit_tol=0.0)
    settling = dataclasses.replace(free, commit_tol=0.01)
    committed = 15
    full = solve_shooting(problem.shooting, free, max_iter=40, committed=committed)
    settled = solve_shooting(problem.shooting, settling, max_iter=40, committed=committed)
    k = settled.iterations
    assert (full.stop_reason, full.iterations) == ("max_iter", 40)
    assert settled.stop_reason == "settled" and 1 < k < 40 and settled.steps[-1] == 1.0
    assert settled.costs == full.costs[:k]
    # the stop's own condition, on the default solve's iterations k - 1 and k
    before, at = (solve_shooting(problem.shooting, free, max_iter=i).xs[1:committed + 1] for i in (k - 1, k))
    assert np.abs(at - before).max() <= 0.01
    with pytest.raises(ConfigError, match="solver.commit_tol must be >= 0"):
        get_task("walk", robot, {"solver.commit_tol": -1.0})
