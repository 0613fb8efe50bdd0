"""The compiled robotics stack is pinned to a pair that works: a real Crocoddyl solve on Digit.

crocoddyl 3.2.1 with pin 4.1.0 returns garbage states or raises MemoryError (docs/dependencies.md).
These tests fail if the installed versions drift from the pins or if the pair stops working.
"""

import importlib.metadata as md
import re
import tomllib
from pathlib import Path

import crocoddyl
import numpy as np
import pinocchio as pin

from opt2skill.model import load_robot
from opt2skill.model.convert import qpos_mj_to_pin

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"
COMPILED_STACK = ("crocoddyl", "pin", "libpinocchio", "mujoco", "mink", "qpsolvers", "daqp")


def test_installed_versions_equal_the_exact_pins():
    deps = tomllib.loads(PYPROJECT.read_text())["project"]["dependencies"]
    pins = {}
    for dep in deps:
        match = re.fullmatch(r"([A-Za-z0-9_.\-]+)==([0-9][^;\s]*)", dep.strip())
        if match:
            pins[match.group(1)] = match.group(2)
    for package in COMPILED_STACK:
        assert package in pins, f"{package} must be pinned with == in pyproject.toml"
        assert md.version(package) == pins[package], (package, md.version(package), pins[package])


def test_crocoddyl_solves_a_squat_on_digit():
    """Both feet in 6D contact, lower the centre of mass by 5 cm in 0.6 s with FDDP."""
    robot = load_robot("digit")
    pm = robot.pin_model
    state = crocoddyl.StateMultibody(pm)
    actuation = crocoddyl.ActuationModelFloatingBase(state)
    assert actuation.nu == robot.nu == 20

    q0 = qpos_mj_to_pin(robot.stand_qpos)
    x0 = np.concatenate([q0, np.zeros(pm.nv)])
    data = pm.createData()
    pin.framesForwardKinematics(pm, data, q0)
    com0 = pin.centerOfMass(pm, data, q0)
    feet = [robot.pin_frame_id(f.sole_site) for f in robot.config.feet]
    placements = [data.oMf[f].copy() for f in feet]

    def running_model(weight_com: float) -> crocoddyl.ActionModelAbstract:
        contacts = crocoddyl.ContactModelMultiple(state, actuation.nu)
        for fid, placement in zip(feet, placements):
            contact = crocoddyl.ContactModel6D(
                state, fid, placement, pin.LOCAL_WORLD_ALIGNED, actuation.nu, np.array([100.0, 20.0])
            )
            contacts.addContact(pm.frames[fid].name, contact)
        costs = crocoddyl.CostModelSum(state, actuation.nu)
        target = com0 - np.array([0.0, 0.0, 0.05])
        costs.addCost("com", crocoddyl.CostModelResidual(state, crocoddyl.ResidualModelCoMPosition(state, target, actuation.nu)), weight_com)
        costs.addCost("x_reg", crocoddyl.CostModelResidual(state, crocoddyl.ResidualModelState(state, x0, actuation.nu)), 1e-2)
        costs.addCost("u_reg", crocoddyl.CostModelResidual(state, crocoddyl.ResidualModelControl(state, actuation.nu)), 1e-4)
        dmodel = crocoddyl.DifferentialActionModelContactFwdDynamics(state, actuation, contacts, costs, 0.0, True)
        return crocoddyl.IntegratedActionModelEuler(dmodel, 0.02)

    problem = crocoddyl.ShootingProblem(x0, [running_model(1e2)] * 30, running_model(1e4))
    solver = crocoddyl.SolverFDDP(problem)
    xs = [x0] * 31
    assert solver.solve(xs, problem.quasiStatic(xs[:-1]), 100)

    xs = np.array(solver.xs)
    assert np.all(np.isfinite(xs)) and solver.stop < 1e-6
    q_end = xs[-1, : pm.nq]
    assert abs(pin.centerOfMass(pm, data, q_end)[2] - (com0[2] - 0.05)) < 0.005
    pin.framesForwardKinematics(pm, data, q_end)
    for fid, placement in zip(feet, placements):
        assert np.linalg.norm(data.oMf[fid].translation - placement.translation) < 1e-3
    # The knees carry the weight (about 53 N m each at stand, docs/robots.md), symmetrically.
    knees = [robot.config.joint_names.index(n) for n in ("left_knee", "right_knee")]
    us = np.array(solver.us)
    assert np.all(us[:, knees] > 20.0) and np.all(us[:, knees] < robot.config.torque_limit[knees])
    assert 40.0 < us[:, knees].mean() < 70.0
    assert np.abs(us[:, knees[0]] - us[:, knees[1]]).max() < 1.0
