"""The walking plan (no optimization): timeline, footholds and swing references."""

import numpy as np
import pytest

from opt2skill.data.record import FRAME_DT
from opt2skill.trajopt.skills.gait import Foothold, GaitSpec, plan_gait, swing_reference

FEET = {
    "left_foot": Foothold("left_foot", np.array([0.0, 0.1, 0.0]), 0.0),
    "right_foot": Foothold("right_foot", np.array([0.0, -0.1, 0.0]), 0.0),
}


def spec(**kw):
    base = dict(speed=1.0, lateral_speed=0.0, yaw_rate=0.0, clearance=0.15, step_duration=0.35,
                double_support=0.2, stand_start=0.5, duration=14.0, stand_end_min=1.0, ramp=1.5)
    return GaitSpec(**{**base, **kw})


def on_grid(t):
    return abs(t / FRAME_DT - round(t / FRAME_DT)) < 1e-9


def test_timeline_fills_the_duration_on_the_frame_grid():
    plan = plan_gait(spec(), FEET, np.zeros(2))
    assert plan.duration == pytest.approx(14.0)
    assert len(plan.steps) == int((14.0 - 0.5 - 1.0) // 0.35)
    assert plan.duration - plan.walk_end >= 1.0 - 1e-9
    for step in plan.steps:
        assert all(on_grid(t) for t in (step.start, step.liftoff, step.touchdown))
    assert [s.swing for s in plan.steps[:3]] == ["left_foot", "right_foot", "left_foot"]


def test_footholds_follow_the_commanded_speed_and_end_side_by_side():
    plan = plan_gait(spec(), FEET, np.zeros(2))
    strides = [b.target.position[0] - a.target.position[0] for a, b in zip(plan.steps[10:20], plan.steps[12:22])]
    assert np.allclose(strides, 2 * 1.0 * 0.35, atol=1e-6)  # cruising: one stride per two steps
    last = {s.swing: s.target for s in plan.steps[-2:]}
    assert last["left_foot"].position[0] == pytest.approx(last["right_foot"].position[0])
    assert plan.velocity[0].tolist() == [0.0, 0.0, 0.0] and np.allclose(plan.velocity[-1], 0.0)


def test_speed_zero_steps_in_place():
    plan = plan_gait(spec(speed=0.0), FEET, np.zeros(2))
    for step in plan.steps:
        assert np.allclose(step.target.position, FEET[step.swing].position)


def test_turning_starts_with_the_inner_foot_and_turns_the_footholds():
    plan = plan_gait(spec(yaw_rate=-0.3), FEET, np.zeros(2))
    assert plan.steps[0].swing == "right_foot"
    assert plan.steps[-1].target.yaw < -1.0


def test_swing_reference_is_a_cubic_with_the_requested_apex():
    plan = plan_gait(spec(), FEET, np.zeros(2))
    step = plan.steps[12]
    start, _, v0 = swing_reference(step, step.liftoff, 0.15)
    end, _, v1 = swing_reference(step, step.touchdown, 0.15)
    apex, _, _ = swing_reference(step, 0.5 * (step.liftoff + step.touchdown), 0.15)
    assert np.allclose(start, step.origin.position) and np.allclose(end, step.target.position)
    assert np.allclose(v0, 0.0) and np.allclose(v1, 0.0)
    assert apex[2] == pytest.approx(0.15)
