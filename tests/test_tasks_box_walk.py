"""Pickup then walk: the box pickup's first phases, then steps with the box held on every node; a
real solve whose robot and box balance, whose hands hold by friction while the feet step, whose
base covers the commanded distance, and whose box the feedback expert carries in MuJoCo."""

import numpy as np
import pytest
from box_support import carried_frames, momentum_rate_residual

from opt2skill.data.validate import validate
from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.tasks import get_task
from opt2skill.trajopt.skills.box_handling import HANDS

# Seed 0's index 0 of the default ranges with a 3-step, 0.2-m walk: accepted (docs/trajopt.md).
PARAMS = dict(board=0.9100657856053599, reach=0.5007914685505548, box_width=0.2720486761968097,
              box_mass=0.31156934486997034, distance=0.2, steps=3, step_duration=0.460663577576718,
              clearance=0.08917986243935994)


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


@pytest.fixture(scope="module")
def solved(robot):
    task = get_task("box_walk", robot, {"solver.keep_gains": True})
    return task, task.solve(PARAMS, seed=0)


def test_bad_walk_parameters_are_refused(robot):
    task = get_task("box_walk", robot)
    with pytest.raises(ConfigError, match=r"2 steps of 0.46\d* s needs 1.6\d m/s, more than max_speed 0.6 m/s.*at most 0.11 m"):
        task.solve({**PARAMS, "distance": 0.3, "steps": 2}, seed=0)
    with pytest.raises(ConfigError, match="box_mass"):  # nothing to carry: no hand forces to learn
        task.solve({**PARAMS, "box_mass": 0.0}, seed=0)
    with pytest.raises(ConfigError, match="steps"):
        task.solve({**PARAMS, "steps": 12}, seed=0)
    with pytest.raises(ConfigError, match="sampling ranges reach a walk too fast: distance = 0.5 m in 3 steps"):
        get_task("box_walk", robot, {"ranges": {"distance": [0.1, 0.5]}})  # refused before any solve
    with pytest.raises(ConfigError, match="max_speed must be in"):
        get_task("box_walk", robot, {"max_speed": 2.0})


def test_the_plan_is_the_pickups_take_then_the_walks_steps_carrying_the_box(robot):
    """Composed, not copied: the first phases are the box pickup's own (same labels, durations,
    contacts, squeeze), then one walking phase per stance and swing, each carrying the box."""
    task = get_task("box_walk", robot)
    pickup = get_task("box_pickup", robot)
    phases = task.plan(PARAMS).phases
    source = pickup.plan({"low": PARAMS["board"], "high": PARAMS["board"] + 0.35, "upward": 1.0,
                          **{k: PARAMS[k] for k in ("reach", "box_width", "box_mass")}}).phases
    take = [p.label for p in source].index("to the other board")  # the pickup's put starts there
    for mine, theirs in zip(phases[:take], source[:take]):
        assert (mine.label, mine.duration, mine.squeeze) == (theirs.label, theirs.duration, theirs.squeeze)
        assert [c.name for c in mine.contacts] == [c.name for c in theirs.contacts]
    walk = phases[take:]
    swings = [p for p in walk if p.label.startswith("swing")]
    assert len(swings) == PARAMS["steps"] and all(len(p.contacts) == 1 for p in swings)
    squeeze = task.squeeze_force(PARAMS["box_mass"])
    assert all(dict(p.payload) == {h: PARAMS["box_mass"] / 2 for h in HANDS} and p.squeeze == squeeze for p in walk)
    assert walk[-1].posture == task.config.walk_posture and phases[0].posture is None


@pytest.mark.slow
def test_pickup_then_walk_is_accepted_the_hands_hold_through_every_step_and_the_expert_carries_the_box(robot, solved):
    task, traj = solved
    names = list(traj.contact_names)
    hands = traj.contact_active[:, [names.index(h) for h in HANDS]].all(axis=1)
    feet = traj.contact_active[:, [names.index(f) for f in ("left_foot", "right_foot")]]
    # the hands touch the box from the squeeze to the end, through every single support
    first = int(np.flatnonzero(hands)[0])
    assert hands[first:-1].all() and (feet[first:-1].sum(axis=1) == 1).sum() > 100  # (the last frame has no step)
    # feet and hands balance the robot; while carried, the hands' forces are the box's weight and
    # momentum rate, also while a foot swings
    robot_res, box_res = momentum_rate_residual(robot, traj, PARAMS["box_mass"])
    impacts = np.any(traj.contact_active[1:] & ~traj.contact_active[:-1], axis=1)
    assert np.abs(robot_res[~impacts]).max() < 1e-6 * 50
    carried = carried_frames(task, traj)[hands[:-1]]
    assert np.abs(box_res[carried]).max() < 1e-6
    # the walk covers the commanded distance, backwards
    gait = task.walk_of(traj.params)
    start = int(round(gait.steps[0].liftoff / 0.005))
    assert traj.qpos[-1, 0] - traj.qpos[start, 0] == pytest.approx(-PARAMS["distance"], abs=0.03)
    errors = task.task_errors(traj)
    result = validate(robot, traj, task_errors=errors)
    assert result["accepted"], result["reasons"]
    assert result["figures"]["replay_feedback_fallen"] == 0.0
    # the expert carries the box in MuJoCo: within 5 cm of the reference's box at every frame
    assert errors["carry_error"]["value"] < 0.05 and errors["hand_friction"]["value"] <= 1.0
