"""Validation on a real solved squat: it passes, and each kind of broken record fails its check."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from opt2skill.data.checks import dynamics_residual
from opt2skill.data.record import build_trajectory
from opt2skill.data.validate import ValidationConfig, validate
from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.tasks import get_task

CONFIG = ValidationConfig().with_overrides({"replay.window": 0.5})


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


@pytest.fixture(scope="module")
def squat(robot):
    task = get_task("squat", robot)
    traj = task.solve({"depth": 0.12}, 0)
    return traj, task.task_errors(traj)


def _rebuilt(robot, traj, qpos=None, torque=None, wrench=None):
    """The record with changed state/torques/wrenches and its derived fields recomputed."""
    out = build_trajectory(
        robot, traj.qpos if qpos is None else qpos, traj.qvel, traj.joint_torque if torque is None else torque,
        traj.contact_wrench if wrench is None else wrench, traj.contact_active, task=traj.task,
        contact_names=traj.contact_names, params=traj.params, seed=traj.seed, ee_names=traj.ee_names,
        solver=traj.solver, provenance=traj.provenance,
    )
    return out


def test_a_real_solve_passes_with_exact_dynamics(robot, squat):
    traj, task_errors = squat
    v = validate(robot, traj, CONFIG, task_errors)
    assert v["accepted"], v["reasons"]
    f = v["figures"]
    # The optimizer's own dynamics hold on its grid and on the 200 Hz frames (rollout completion).
    assert f["id_residual_knots_max"] < 1e-8 and f["id_residual_frames_max"] < 1e-8
    assert f["foot_slip"] < 1.0 and f["replay_fallen_windows"] == 0 and f["replay_fall_time"] is None
    assert f["task.depth_error"] < 0.01 and v["units"]["task.depth_error"] == "m"
    assert len(v["replay_windows"]) >= 3 and v["time"] > 0


def test_knot_residual_sees_wrong_forces(robot, squat):
    traj, _ = squat
    k, nq = traj.knots, robot.pin_model.nq
    x = k["x"]
    args = (robot, x[:-1, :nq], x[:-1, nq:], x[1:, nq:], k["dt"], k["u"])
    exact = dynamics_residual(*args, k["contact_force"], traj.contact_names)
    wrong = dynamics_residual(*args, k["contact_force"] * 1.01, traj.contact_names)
    assert np.abs(exact).max() < 1e-8 and np.abs(wrong).max() > 1.0


def test_scaled_torques_fail_inverse_dynamics(robot, squat):
    traj, task_errors = squat
    v = validate(robot, replace(traj, joint_torque=1.5 * traj.joint_torque), CONFIG, task_errors)
    assert not v["accepted"]
    assert "id_residual_frames_max" in v["reasons"] and v["figures"]["id_residual_frames_max"] > 10.0


def test_a_moved_stance_foot_fails_slip(robot, squat):
    traj, task_errors = squat
    qpos = traj.qpos.copy()
    hip_yaw = 7 + robot.config.joint_names.index("left_hip_yaw")
    qpos[:, hip_yaw] += np.linspace(0.0, 0.2, len(qpos))  # the left sole turns about the hip while in contact
    v = validate(robot, _rebuilt(robot, traj, qpos=qpos), CONFIG, task_errors)
    assert "foot_slip" in v["reasons"] and v["figures"]["foot_slip"] > 10.0


def test_contact_and_limit_violations_are_measured_in_their_units(robot, squat):
    traj, task_errors = squat
    wrench = traj.contact_wrench.copy()
    wrench[100, 0, 0] += 250.0  # tangential force far outside mu = 0.7 at ~230 N normal
    wrench[200, 1, 4] += 0.2 * wrench[200, 1, 2]  # CoP 0.2 m behind the sole centre (half length 0.1175)
    torque = traj.joint_torque.copy()
    knee = robot.config.joint_names.index("left_knee")
    torque[50, knee] = robot.config.torque_limit[knee] + 3.0
    v = validate(robot, _rebuilt(robot, traj, torque=torque, wrench=wrench), CONFIG, task_errors)
    f = v["figures"]
    assert {"friction_violation", "cop_violation", "torque_violation"} <= set(v["reasons"])
    assert f["torque_violation"] == pytest.approx(3.0)
    cop_x = -traj.contact_wrench[200, 1, 4] / traj.contact_wrench[200, 1, 2]  # soles flat: world axes = sole axes
    assert f["cop_violation"] == pytest.approx(abs(cop_x - 0.2) - 0.1175, abs=1e-4)
    assert f["friction_violation"] > 50.0


def test_tampered_derived_fields_fail(robot, squat):
    traj, task_errors = squat
    v = validate(robot, replace(traj, com=traj.com + 0.01), CONFIG, task_errors)
    assert v["reasons"] == ["derived_fields_error"]


def test_replay_detects_a_fall(robot, squat):
    """A reference floating 0.4 m above the floor cannot be followed: the robot drops."""
    traj, _ = squat
    qpos = traj.qpos.copy()
    qpos[:, 2] += 0.4
    v = validate(robot, _rebuilt(robot, traj, qpos=qpos), CONFIG)
    assert v["figures"]["replay_fallen_windows"] == 1.0 and v["figures"]["replay_fall_time"] < 0.5
    assert "replay_fallen_windows" in v["reasons"]


def test_task_errors_and_limits_are_judged(robot, squat):
    traj, _ = squat
    errors = {"speed_error": {"value": 0.3, "limit": 0.1, "unit": "m/s"}}
    v = validate(robot, traj, CONFIG.with_overrides({"foot_slip": "none", "cop_violation": 0.0}), errors)
    assert v["reasons"] == ["task.speed_error"] and v["limits"]["foot_slip"] is None
    with pytest.raises(ConfigError, match="unknown validation limit 'slip'"):
        CONFIG.with_overrides({"slip": 1})
    with pytest.raises(ConfigError, match="must be a number"):
        CONFIG.with_overrides({"foot_slip": "abc"})
    with pytest.raises(ConfigError, match="unknown replay setting"):
        CONFIG.with_overrides({"replay.windw": 1})


def _feedback_plain(replayer):
    """The feedback replay's law written plainly (the form `Replayer.feedback` is optimized from)."""
    import mujoco
    import pinocchio as pin

    from opt2skill.model.convert import qpos_mj_to_pin, qvel_mj_to_pin

    r, tr, cfg, pm = replayer, replayer.traj, replayer.robot.config, replayer.robot.pin_model
    ref = replayer.feedback_references()
    qpos_ref, q_ref, v_ref, tau_ref, node, gains = (ref[k] for k in ("qpos_ref", "q_ref", "v_ref", "tau_ref", "node", "gains"))
    nstep = len(qpos_ref)
    m, d = r.model, r.data
    mujoco.mj_resetData(m, d)
    d.qpos[: r.nq], d.qvel[: r.nv] = tr.qpos[0], tr.qvel[0]
    qpos = np.empty((nstep, r.nq))
    for i in range(nstep):
        qpos_now, qvel_now = d.qpos[: r.nq], d.qvel[: r.nv]
        q = qpos_mj_to_pin(qpos_now)
        dx = np.concatenate([pin.difference(pm, q_ref[i], q), qvel_mj_to_pin(qpos_now, qvel_now) - v_ref[i]])
        u = tau_ref[i] - gains[node[i]] @ dx + r._joint_losses(qvel_now[6:])
        d.ctrl[:] = qpos_ref[i, 7:] + (u + cfg.kd * v_ref[i, 6:]) / cfg.kp
        mujoco.mj_step(m, d)
        qpos[i] = d.qpos[: r.nq]
    return qpos


def test_feedback_replay_is_bitwise_its_plain_law(robot):
    """`Replayer.feedback` is written for speed; its states are exactly those of the plain law,
    also when the start is pushed so the feedback acts (a figure of the validation must not move)."""
    from opt2skill.data.replay import Replayer

    task = get_task("squat", robot, {"solver.keep_gains": True})
    traj = task.solve({"depth": 0.1}, 0)
    qvel = traj.qvel.copy()
    qvel[0, :3] += [0.2, -0.1, 0.05]  # a push: the base moves off the reference at once
    qvel[0, 8] += 1.0
    pushed = replace(traj, qvel=qvel)
    for record in (traj, pushed):
        fast, _ = Replayer(robot, record, CONFIG.replay, use_compiled=False).feedback_states()
        plain = _feedback_plain(Replayer(robot, record, CONFIG.replay))
        assert fast.shape == plain.shape
        assert np.array_equal(fast, plain)


def test_the_compiled_feedback_replay_follows_the_python_loop(robot):
    """The C++ loop (trajopt/native/feedback_replay.hpp) takes the Python loop's states to round-off,
    with the servos' PD or without, and stops at the same step when the robot falls."""
    from opt2skill.data.replay import Replayer

    task = get_task("squat", robot, {"solver.keep_gains": True})
    traj = task.solve({"depth": 0.1}, 0)
    if not Replayer(robot, traj, CONFIG.replay).compiled:
        pytest.skip("the compiled module is not built here (no C++ compiler)")
    qvel = traj.qvel.copy()
    qvel[0, :3] += [0.2, -0.1, 0.05]
    pushed = replace(traj, qvel=qvel)
    qvel = traj.qvel.copy()
    qvel[0, :3] += [3.0, 0.0, 0.0]  # 3 m/s sideways at the start: the feedback cannot hold it
    falling = replace(traj, qvel=qvel)
    for record, pd in ((traj, True), (pushed, True), (pushed, False), (falling, True)):
        settings = replace(CONFIG.replay, feedback_pd=pd)
        qpos, sensors, props = Replayer(robot, record, settings).feedback_states(props=True)
        ref_qpos, ref_sensors, ref_props = Replayer(robot, record, settings, use_compiled=False).feedback_states(
            props=True)
        assert qpos.shape == ref_qpos.shape and props.shape == ref_props.shape
        np.testing.assert_allclose(qpos, ref_qpos, rtol=0, atol=1e-9)
        np.testing.assert_allclose(sensors, ref_sensors, rtol=1e-7, atol=1e-6)
        assert not np.array_equal(qpos[-1], record.qpos[-1])  # it moved
    fell, _ = Replayer(robot, falling, CONFIG.replay).feedback_states()
    assert len(fell) < len(Replayer(robot, traj, CONFIG.replay).feedback_states()[0])  # the fall stops it early


def test_the_validation_replays_a_model_with_the_soles_sensors_alone(robot):
    """The validation's replays read only the soles' positions: their model computes no other sensor,
    and every replay (windows, the whole motion open loop, under the feedback law) gives the same
    states and figures to the bit as the model with every sensor; a sensor the robot lacks is named."""
    from opt2skill.data.replay import Replayer
    from opt2skill.scene.build import build_model

    traj = get_task("squat", robot, {"solver.keep_gains": True}).solve({"depth": 0.1}, 0)
    pushed = replace(traj, qvel=traj.qvel + np.r_[0.4, -0.2, 0.0, np.zeros(traj.qvel.shape[1] - 3)])
    for record in (traj, pushed):
        full, feet = Replayer(robot, record, CONFIG.replay), Replayer(robot, record, CONFIG.replay, all_sensors=False)
        assert feet.layout is None and feet.model.nsensordata == 3 * len(robot.config.feet) < full.model.nsensordata
        assert feet.windows() == full.windows() and feet.full() == full.full()
        assert feet.feedback() == full.feedback() is not None
        qpos, sensors = feet.feedback_states()
        full_qpos, full_sensors = full.feedback_states()
        np.testing.assert_array_equal(qpos, full_qpos)
        np.testing.assert_array_equal(sensors, full_sensors[:, full.foot_columns.ravel()])
    assert feet.windows()[0].foot_error > 0.0
    with pytest.raises(KeyError, match="has no sensor ee_nose"):
        build_model(robot, traj.scene, ["ee_nose"])
