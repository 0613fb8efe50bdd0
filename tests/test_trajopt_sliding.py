"""Shared pieces the desk tasks added: hand paths' derivatives, sliding point contacts' Baumgarte
references, contact radii, the height barrier, and props' friction in MuJoCo."""

import crocoddyl
import mujoco
import numpy as np
import pinocchio as pin
import pytest

from opt2skill.model import load_robot
from opt2skill.scene.build import build_model
from opt2skill.scene.description import Scene
from opt2skill.scene.props import Desk
from opt2skill.trajopt.costs import Terms
from opt2skill.trajopt.phases import Contact, Phase, ProblemBuilder
from opt2skill.trajopt.settings import ContactSettings, FeasibilityWeights
from opt2skill.trajopt.skills.desk import Stand
from opt2skill.trajopt.skills.manipulation import HandPath, contact_radius, sliding_contact


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


def test_a_hand_paths_velocity_and_acceleration_are_its_positions_derivatives():
    path = HandPath({"h": np.zeros(3)}, {"h": np.array([0.2, -0.1, 0.05])}, t0=1.0, duration=0.8)
    h = 1e-5
    for t in (1.1, 1.4, 1.75):
        p, v, a = path.motion("h", t)
        assert p == pytest.approx(path.at(t)["h"])
        assert v == pytest.approx((path.at(t + h)["h"] - path.at(t - h)["h"]) / (2 * h), abs=1e-6)
        assert a == pytest.approx((path.motion("h", t + h)[1] - path.motion("h", t - h)[1]) / (2 * h), abs=1e-4)
    assert not np.any(path.motion("h", 0.5)[1]) and not np.any(path.motion("h", 2.0)[2])  # at rest outside


def test_a_sliding_contacts_reference_leads_its_path_by_the_baumgarte_feedforward(robot):
    contact = ContactSettings()
    builder = ProblemBuilder(robot, contact, FeasibilityWeights())
    stand = Stand.of(robot)
    start = stand.home["right_hand"]
    path = HandPath({"right_hand": start}, {"right_hand": start + [0.1, 0.0, 0.0]}, 0.0, 0.4)
    hand = sliding_contact("right_hand", path, np.array([0.0, 0.0, 1.0]), min_normal_force=0.0)
    phase = Phase(0.4, stand.feet + (hand,), lambda knot, terms: [])
    problem = builder.build([phase], stand.x0, 0.02, with_costs=False)
    kp, kd = contact.baumgarte_kp, contact.baumgarte_kd
    for node, model in zip(problem.nodes[:-1], problem.shooting.runningModels):
        p, v, a = path.motion("right_hand", node.time)
        reference = model.differential.contacts.contacts["right_hand"].contact.reference
        assert reference == pytest.approx(p + (kd * v + a) / kp)


def test_contact_radii_are_the_collision_capsules_and_spheres_at_the_sites(robot):
    assert contact_radius(robot, "left_hand") == pytest.approx(0.04)  # the hand's sphere
    assert contact_radius(robot, "right_elbow") == pytest.approx(0.04)  # the upper arm's capsule end
    assert contact_radius(robot, "left_foot") == 0.0  # a sole is a box


def test_the_height_barrier_costs_nothing_above_and_grows_below(robot):
    state = crocoddyl.StateMultibody(robot.pin_model)
    terms = Terms(state, 20, robot)
    x = np.concatenate([robot.stand_q_pin, np.zeros(robot.nv)])
    data = pin.Data(robot.pin_model)
    pin.framesForwardKinematics(robot.pin_model, data, robot.stand_q_pin)
    z = data.oMf[robot.pin_frame_id("left_elbow_site")].translation[2]
    costs = []
    for height in (z - 0.1, z + 0.01, z + 0.02):
        cost = terms.above("left_elbow_site", height)
        shared = crocoddyl.DataCollectorMultibody(pin.Data(robot.pin_model))
        cd = cost.createData(shared)
        pin.framesForwardKinematics(robot.pin_model, shared.pinocchio, robot.stand_q_pin)
        cost.calc(cd, x, np.zeros(20))
        costs.append(cd.cost)
    assert costs[0] == 0.0 and 0.0 < costs[1] < costs[2]


def test_a_props_friction_is_its_contacts_friction_in_mujoco(robot):
    """Props' geoms take priority: a hand (friction 1) on a whiteboard (0.3) slides with 0.3."""
    model = build_model(robot, Scene(props=(Desk(pos=(0.56, 0.0), height=0.9, friction=0.3),)))
    desk = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "desk/top")
    hand = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "right_hand")
    assert model.geom_priority[desk] > model.geom_priority[hand]
    assert model.geom_friction[desk, 0] == pytest.approx(0.3) and model.geom_friction[hand, 0] == pytest.approx(1.0)


def test_a_touchdown_impulse_holds_the_fixed_contacts_that_continue_through_it(robot):
    """The elbow touching down while the feet stand and a hand slides: the impulse model has the
    feet (they are rigid at the impact, so it leaves them at rest) and the elbow, not the sliding
    hand (an impulse would stop it)."""
    builder = ProblemBuilder(robot, ContactSettings(), FeasibilityWeights())
    stand = Stand.of(robot)
    start = stand.home["right_hand"]
    path = HandPath({"right_hand": start}, {"right_hand": start + [0.1, 0.0, 0.0]}, 0.0, 0.4)
    hand = sliding_contact("right_hand", path, np.array([0.0, 0.0, 1.0]), min_normal_force=0.0)
    elbow = Contact("left_elbow", pin.SE3(np.eye(3), stand.home["left_elbow"]), flat=False)
    phases = [Phase(0.2, stand.feet + (hand,), lambda knot, terms: []),
              Phase(0.2, stand.feet + (hand, elbow), lambda knot, terms: [])]
    problem = builder.build(phases, stand.x0, 0.02, with_costs=False)
    [k] = [k for k, n in enumerate(problem.nodes) if n.kind == "impulse"]
    feet = tuple(c.name for c in stand.feet)
    assert problem.nodes[k].touching == ("left_elbow",)
    assert set(problem.nodes[k].contacts) == {*feet, "left_elbow"}
    # Coming in with the feet at rest and the rest of the robot moving: after the impact the feet
    # and the elbow are at rest (Crocoddyl's impulse dynamics, not a bookkeeping of names).
    pm, pd = robot.pin_model, robot.pin_model.createData()
    q = robot.stand_q_pin
    pin.computeJointJacobians(pm, pd, q)
    pin.updateFramePlacements(pm, pd)
    jac = lambda name: pin.getFrameJacobian(pm, pd, builder.frame_id(name), pin.LOCAL_WORLD_ALIGNED)
    J_feet = np.vstack([jac(f) for f in feet])
    rng = np.random.default_rng(0)
    v = rng.normal(0.0, 0.3, robot.nv)
    v -= np.linalg.pinv(J_feet) @ (J_feet @ v)  # feet at rest before the impact
    model, data = problem.shooting.runningModels[k], problem.shooting.runningDatas[k]
    model.calc(data, np.concatenate([q, v]))
    v_after = data.xnext[pm.nq:]
    assert np.abs(J_feet @ v_after).max() < 1e-8
    assert np.abs(jac("left_elbow")[:3] @ v_after).max() < 1e-8
    assert np.abs(jac("left_elbow")[:3] @ v).max() > 0.05  # it did come in moving
    # the old rule, kept for the box pickup: only the touching-down contact is in the impulse
    old = ProblemBuilder(robot, ContactSettings(impacts_hold=False), FeasibilityWeights()).build(
        phases, stand.x0, 0.02, with_costs=False)
    assert [n.contacts for n in old.nodes if n.kind == "impulse"] == [("left_elbow",)]
