"""Two hands squeezing a held object inside the optimizer's dynamics (`trajopt.squeeze`): the
actuation adds the squeeze pair's generalized force with its exact derivative, and a real Box-FDDP
solve's torques hold it, so the robot-only equations of motion balance with the hands' forces."""

import crocoddyl
import numpy as np
import pinocchio as pin
import pytest

from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.trajopt.frames import contact_wrenches
from opt2skill.trajopt.phases import Phase, ProblemBuilder
from opt2skill.trajopt.settings import ContactSettings, FeasibilityWeights
from opt2skill.trajopt.skills.desk import Stand
from opt2skill.trajopt.skills.manipulation import GRAVITY, hold_squeeze
from opt2skill.trajopt.squeeze import SqueezeActuation

HANDS = ("left_hand", "right_hand")


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


def _hand_frames(robot):
    return tuple(robot.pin_frame_id(robot.config.end_effectors[h]) for h in HANDS)


def _pair_force(robot, q, squeeze):
    """J_1^T (s a) + J_2^T (-s a), a the unit vector from the right hand to the left."""
    pm = robot.pin_model
    pd = pm.createData()
    pin.computeJointJacobians(pm, pd, q)
    pin.updateFramePlacements(pm, pd)
    left, right = _hand_frames(robot)
    axis = pd.oMf[left].translation - pd.oMf[right].translation
    axis /= np.linalg.norm(axis)
    jac = [pin.getFrameJacobian(pm, pd, f, pin.LOCAL_WORLD_ALIGNED)[:3] for f in (left, right)]
    return squeeze * (jac[0] - jac[1]).T @ axis


def test_the_squeeze_actuation_adds_the_hands_force_pair_with_its_exact_derivative(robot):
    state = crocoddyl.StateMultibody(robot.pin_model)
    actuation = SqueezeActuation(state, _hand_frames(robot), 60.0)
    data = actuation.createData()
    rng = np.random.default_rng(0)
    q = robot.stand_q_pin.copy()
    q[7:] += rng.normal(0.0, 0.2, len(q) - 7)
    x, u = np.r_[q, rng.normal(size=robot.nv)], rng.normal(size=actuation.nu)
    actuation.calc(data, x, u)
    pair = _pair_force(robot, q, 60.0)
    assert np.abs(pair[:6]).max() < 1e-12  # no net force or moment on the robot
    assert np.abs(pair).max() > 5.0  # N m on the arms
    assert data.tau == pytest.approx(np.r_[np.zeros(6), u] + pair, abs=1e-10)
    actuation.calcDiff(data, x, u)
    numeric = np.zeros((robot.nv, 2 * robot.nv))
    for j in range(2 * robot.nv):
        step = np.zeros(2 * robot.nv)
        step[j] = 1e-6
        plus, minus = actuation.createData(), actuation.createData()
        actuation.calc(plus, state.integrate(x, step), u)
        actuation.calc(minus, state.integrate(x, -step), u)
        numeric[:, j] = (plus.tau - minus.tau) / 2e-6
    assert np.abs(data.dtau_dx - numeric).max() < 1e-6 * np.abs(numeric).max()
    actuation.commands(data, x, data.tau)
    assert data.u == pytest.approx(u, abs=1e-10)


def test_a_squeeze_needs_a_payload_at_two_points(robot):
    builder = ProblemBuilder(robot, ContactSettings(), FeasibilityWeights())
    stand = Stand.of(robot)
    phase = Phase(0.1, stand.feet, lambda knot, terms: [], squeeze=20.0)
    with pytest.raises(ConfigError, match="payload"):
        builder.build([phase], stand.x0, 0.02)


def test_a_solve_holding_a_heavy_box_puts_the_squeeze_in_its_torques(robot):
    """Standing with 2.5 kg at each hand and the squeeze friction needs: at every node the solver's
    torques, the feet's wrenches and the hands' forces (the box's share of weight and acceleration
    plus the squeeze pair) satisfy the robot-only equations of motion. Without the squeeze in the
    solve the arms would miss its torques (tens of N m)."""
    pm = robot.pin_model
    squeeze = hold_squeeze(5.0, mu=0.56, margin=1.5, acceleration=3.0)
    assert squeeze == pytest.approx(1.5 * 2.5 * 12.81 / 0.56)
    builder = ProblemBuilder(robot, ContactSettings(), FeasibilityWeights())
    stand = Stand.of(robot)

    def costs(knot, terms):
        return [("state", terms.state_reg(stand.x0, np.ones(2 * robot.nv)), 1.0),
                ("control", terms.control_reg(1e-3), 1.0)]

    payload = tuple((h, 2.5) for h in HANDS)
    phase = Phase(0.2, stand.feet, costs, payload=payload, squeeze=squeeze)
    problem = builder.build([phase], stand.x0, 0.02)
    solver = crocoddyl.SolverBoxFDDP(problem.shooting)
    assert solver.solve([stand.x0] * (len(problem.nodes)), [], 30)
    xs, us = np.array(solver.xs), np.array(solver.us)
    limit = robot.config.torque_limit * FeasibilityWeights().torque_limit_scale
    assert np.all(np.abs(us) <= limit + 1e-9)
    pd = pm.createData()
    nq, nv = pm.nq, pm.nv
    pair_size = []
    for k, (node, model, data) in enumerate(zip(problem.nodes[:-1], problem.shooting.runningModels,
                                                problem.shooting.runningDatas)):
        q, v = xs[k, :nq], xs[k, nq:]
        model.calc(data, xs[k], us[k])
        a = data.differential.xout
        wrenches = np.zeros((len(problem.contact_names), 6))
        contact_wrenches(data, problem, node.contacts, wrenches)
        pin.forwardKinematics(pm, pd, q, v, a)
        pin.computeJointJacobians(pm, pd, q)
        pin.updateFramePlacements(pm, pd)
        generalized = np.zeros(nv)
        for name, w in zip(problem.contact_names, wrenches):
            generalized += pin.getFrameJacobian(pm, pd, problem.frame_ids[name], pin.LOCAL_WORLD_ALIGNED).T @ w
        for fid in _hand_frames(robot):
            share = 2.5 * (GRAVITY - pin.getFrameClassicalAcceleration(pm, pd, fid, pin.LOCAL_WORLD_ALIGNED).linear)
            generalized += pin.getFrameJacobian(pm, pd, fid, pin.LOCAL_WORLD_ALIGNED)[:3].T @ share
        pair = _pair_force(robot, q, squeeze)
        residual = pin.rnea(pm, pd, q, v, a) - np.r_[np.zeros(6), us[k]] - generalized - pair
        assert np.abs(residual).max() < 1e-6
        pair_size.append(np.abs(pair).max())
    assert min(pair_size) > 10.0  # N m: the squeeze is no rounding error in the torques above
