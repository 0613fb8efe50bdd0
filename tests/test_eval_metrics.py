"""Every Table III/IV metric on hand-made trajectories whose answers are known in closed form."""

import dataclasses
import math

import numpy as np
import pytest

from opt2skill.data.record import FRAME_DT, Trajectory
from opt2skill.eval.metrics import tracking_errors
from opt2skill.eval.stats import paired_wilcoxon, success_rate, summarize

N = 2001  # 10 s at 200 Hz
EE = ("left_hand", "right_hand", "left_foot", "right_foot")


def yaw_quat(yaw):
    yaw = np.asarray(yaw, dtype=float)
    return np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], -1)


def straight_walk(heading=0.0, speed=1.0, n=N):
    """Base moving at `speed` along `heading`, joints at zero, fixed hand/foot offsets and forces."""
    t = np.arange(n) * FRAME_DT
    qpos = np.zeros((n, 27))
    qpos[:, 0], qpos[:, 1] = speed * t * math.cos(heading), speed * t * math.sin(heading)
    qpos[:, 2] = 1.0
    qpos[:, 3:7] = yaw_quat(np.full(n, heading))
    base_lin_vel = np.zeros((n, 3))
    base_lin_vel[:, 0] = speed
    ee_base = np.tile(np.array([[0.2, 0.3, 0.0], [0.2, -0.3, 0.0], [0.0, 0.1, -1.0], [0.0, -0.1, -1.0]]), (n, 1, 1))
    wrench = np.zeros((n, 2, 6))
    wrench[:, :, 2] = 235.0
    return Trajectory(
        time=t, qpos=qpos, qvel=np.zeros((n, 26)), base_lin_vel=base_lin_vel, base_ang_vel=np.zeros((n, 3)),
        joint_torque=np.zeros((n, 20)), contact_wrench=wrench, contact_active=np.ones((n, 2), bool),
        ee_pos=ee_base.copy(), ee_pos_base=ee_base, com=qpos[:, :3].copy(), task="walk", robot="digit",
        contact_names=("left_foot", "right_foot"), ee_names=EE, params={}, seed=0,
    )


def perturbed(ref, heading=0.0, along=0.1, lateral=0.2, yaw=0.05):
    """Known errors: joints +0.1 rad, vx +5 cm/s, wz +0.2 rad/s, hands 5 cm, feet 2 cm, forces 5 N,
    torques 2 N m; final position off by `along`/`lateral` in the heading frame, final yaw by `yaw`."""
    trk = straight_walk(heading=heading, n=ref.num_frames)
    trk.qpos[:, 7:] += 0.1
    trk.base_lin_vel[:, 0] += 0.05
    trk.base_ang_vel[:, 2] += 0.2
    trk.ee_pos_base[:, :2] += [0.03, 0.04, 0.0]
    trk.ee_pos_base[:, 2:] += [0.0, 0.0, 0.02]
    trk.contact_wrench[..., :3] += [3.0, 4.0, 0.0]
    trk.joint_torque += 2.0
    c, s = math.cos(heading), math.sin(heading)
    trk.qpos[-1, :2] += along * np.array([c, s]) + lateral * np.array([-s, c])
    trk.qpos[-1, 3:7] = yaw_quat(heading + yaw)
    return trk


@pytest.mark.parametrize("heading", [0.0, math.pi / 2, -2.5])
def test_every_metric_has_its_known_value(heading):
    ref = straight_walk(heading)
    e = tracking_errors(ref, perturbed(ref, heading))
    path = 1.0 * (N - 1) * FRAME_DT  # 10 m
    assert e.E_joint == pytest.approx(0.1)
    assert e.E_vel_x == pytest.approx(5.0)  # cm/s
    assert e.E_vel_yaw == pytest.approx(0.2)
    assert e.E_ee_hand == pytest.approx(5.0)  # cm
    assert e.E_ee_foot == pytest.approx(2.0)
    assert e.E_pos_x == pytest.approx(100 * 0.1 / path)  # 1 %
    assert e.pace == pytest.approx(1 + 0.1 / path)  # ahead of the reference
    assert e.E_pos_y == pytest.approx(1000 * 0.2 / N)  # mm per step
    assert e.E_yaw == pytest.approx(1000 * 0.05 / N)  # mrad per step
    assert e.E_force == pytest.approx(5.0)
    assert e.E_torque == pytest.approx(2.0)
    assert e.frames == N and not e.fell


def test_perfect_tracking_is_zero_and_yaw_wraps():
    ref = straight_walk(heading=math.pi - 0.01)
    trk = straight_walk(heading=math.pi - 0.01)
    trk.qpos[-1, 3:7] = yaw_quat(-math.pi + 0.01)  # 0.02 rad across the +-pi seam
    e = tracking_errors(ref, trk)
    assert e.E_joint == e.E_ee_foot == e.E_pos_x == e.E_force == 0.0
    assert e.E_yaw == pytest.approx(1000 * 0.02 / N)


def test_a_kinematic_reference_has_no_force_or_torque_error():
    """IK and human records carry zero torques and forces as placeholders: no error against them."""
    ref = dataclasses.replace(straight_walk(), has_dynamics=False)
    e = tracking_errors(ref, perturbed(ref))
    assert math.isnan(e.E_force) and math.isnan(e.E_torque)
    assert e.E_joint == pytest.approx(0.1) and e.E_ee_foot == pytest.approx(2.0)


def test_pace_tells_an_overshoot_from_a_lag_that_e_pos_x_cannot():
    ref = straight_walk()
    ahead, behind = (tracking_errors(ref, perturbed(ref, along=d)) for d in (0.5, -0.5))
    assert ahead.E_pos_x == pytest.approx(behind.E_pos_x) == pytest.approx(5.0)
    assert ahead.pace == pytest.approx(1.05) and behind.pace == pytest.approx(0.95)


def test_lead_is_the_speed_ahead_of_the_reference_whatever_the_paths_length():
    """The same 0.1 m/s ahead over 10 s: E_pos-x 100 % on a 0.1 m/s walk, 10 % on a 1 m/s walk;
    the lead 0.1 m/s on both, and on a walk in place, where E_pos-x is undefined."""
    seconds = (N - 1) * FRAME_DT
    leads = {}
    for speed in (0.1, 1.0, 0.0):
        ref, tracked = straight_walk(speed=speed), straight_walk(speed=speed)
        tracked.qpos[-1, 0] += 0.1 * seconds
        leads[speed] = tracking_errors(ref, tracked)
    assert leads[0.1].E_pos_x == pytest.approx(100.0) and leads[1.0].E_pos_x == pytest.approx(10.0)
    assert math.isnan(leads[0.0].E_pos_x)
    assert all(e.lead == pytest.approx(0.1) for e in leads.values())
    ref = straight_walk()
    assert tracking_errors(ref, perturbed(ref, along=-0.5)).lead == pytest.approx(-0.5 / seconds)


@pytest.mark.parametrize("heading", [0.0, math.pi - 0.01])
def test_turn_tells_left_from_right_that_e_yaw_cannot(heading):
    ref = straight_walk(heading)
    left, right = (tracking_errors(ref, perturbed(ref, heading, yaw=y)) for y in (0.05, -0.05))
    assert left.E_yaw == pytest.approx(right.E_yaw) == pytest.approx(1000 * 0.05 / N)
    assert left.turn == pytest.approx(0.05) and right.turn == pytest.approx(-0.05)  # across the +-pi seam too


def test_stepping_in_place_has_no_path_percentage():
    ref = straight_walk(speed=0.0)
    e = tracking_errors(ref, perturbed(ref))
    assert math.isnan(e.E_pos_x) and math.isnan(e.pace)
    assert e.E_pos_y == pytest.approx(1000 * 0.2 / N)


def test_a_fall_is_compared_on_the_frames_it_has():
    ref = straight_walk()
    trk = perturbed(ref)
    short = straight_walk(n=500)
    short.qpos[:, 7:] += 0.3
    e = tracking_errors(ref, short, fell=True)
    assert e.frames == 500 and e.fell and e.E_joint == pytest.approx(0.3)
    with pytest.raises(ValueError, match="frames"):
        tracking_errors(straight_walk(n=100), trk)


def test_summary_mean_standard_error_success_and_wilcoxon():
    ref = straight_walk()
    rollouts = [tracking_errors(ref, perturbed(ref, along=a)) for a in (0.1, 0.2, 0.3, 0.4)]
    summary = summarize(rollouts)
    values = 100 * np.array([0.1, 0.2, 0.3, 0.4]) / 10.0
    assert summary["E_pos_x"].mean == pytest.approx(values.mean())
    assert summary["E_pos_x"].se == pytest.approx(values.std(ddof=1) / 2.0)
    assert summary["E_pos_x"].n == 4
    flat = [tracking_errors(straight_walk(speed=0.0), perturbed(straight_walk(speed=0.0)))] * 3
    assert summarize(flat)["E_pos_x"].n == 0  # undefined values are skipped, not zeros
    fallen = rollouts[:3] + [tracking_errors(ref, straight_walk(n=50), fell=True)]
    assert success_rate(fallen) == 0.75

    better = [tracking_errors(ref, perturbed(ref, along=a / 10)) for a in np.linspace(0.1, 0.9, 9)]
    worse = [tracking_errors(ref, perturbed(ref, along=a)) for a in np.linspace(0.1, 0.9, 9)]
    p = paired_wilcoxon(better, worse)
    assert p["E_pos_x"] < 0.01  # all nine pairs differ the same way
    assert math.isnan(p["E_joint"])  # identical: no test
    with pytest.raises(ValueError, match="same references"):
        paired_wilcoxon(better, worse[:3])
