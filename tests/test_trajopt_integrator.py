"""The matched integrator (its Python model): its step and derivatives on a real contact-dynamics
node of a walk. The compiled model is checked against this one in tests/test_trajopt_native.py."""

import gc
import weakref

import crocoddyl
import numpy as np
import pytest

from opt2skill.data.record import FRAME_DT
from opt2skill.model import load_robot
from opt2skill.trajopt.integrator import MatchedEulerModel
from opt2skill.tasks import get_task


@pytest.fixture(scope="module")
def node():
    """A single-support node (one 6D contact, the walk's costs and limits) of a real walk problem."""
    robot = load_robot("digit")
    task = get_task("walk", robot, {"steps": 2, "duration": 1.5})
    plan = task.plan(task.param_space().sample(0, 3))
    problem = task.builder.build(plan.phases, plan.x0, 0.03, integrator="matched")
    k = next(i for i, n in enumerate(problem.nodes) if n.kind == "running" and len(n.contacts) == 1)
    built = problem.shooting.runningModels[k]  # compiled where it builds (tests/test_trajopt_native.py)
    assert built.substeps >= 5
    model = MatchedEulerModel(built.differential, built.dt, built.substeps, share_data=True)
    rng = np.random.default_rng(4)
    x = plan.x0.copy()
    x[3:7] = [0.05, -0.03, 0.2, 1.0] / np.linalg.norm([0.05, -0.03, 0.2, 1.0])  # a turned, tilted base
    x[7:27] += rng.normal(scale=0.1, size=20)
    x[27:] = rng.normal(scale=0.8, size=26)
    u = rng.normal(scale=20.0, size=20)
    return model, x, u


def test_joints_move_as_the_200_hz_substeps_with_the_acceleration_held(node):
    model, x, u = node
    data = model.createData()
    model.calc(data, x, u)
    nq, nv = 27, 26
    a = np.array(data.differential.xout)
    q, v = x[7:nq].copy(), x[nq + 6 :].copy()
    for _ in range(model.substeps):  # semi-implicit Euler at the frame period
        v = v + a[6:] * FRAME_DT
        q = q + v * FRAME_DT
    assert np.abs(data.xnext[7:nq] - q).max() < 1e-12
    assert np.abs(data.xnext[nq + 6 :] - v).max() < 1e-12
    # Crocoddyl's Euler at dt moves the joints by a dt^2 more than the first substep; the matched step is in between.
    euler = crocoddyl.IntegratedActionModelEuler(model.differential, model.dt)
    euler_data = euler.createData()
    euler.calc(euler_data, x, u)
    assert np.abs(euler_data.xnext[7:nq] - data.xnext[7:nq]).max() > 1e-3
    assert abs(data.cost - euler_data.cost) < 1e-9 * abs(euler_data.cost)


def test_derivatives_match_finite_differences(node):
    shared, x, u = node
    model = MatchedEulerModel(shared.differential, shared.dt, shared.substeps)  # numerical differences need own datas
    data = model.createData()
    model.calc(data, x, u)
    model.calcDiff(data, x, u)
    numeric = crocoddyl.ActionModelNumDiff(model, True)
    numeric_data = numeric.createData()
    numeric.calc(numeric_data, x, u)
    numeric.calcDiff(numeric_data, x, u)
    scale_x, scale_u = np.abs(numeric_data.Fx).max(), np.abs(numeric_data.Fu).max()
    assert np.abs(data.Fx - numeric_data.Fx).max() < 1e-5 * scale_x
    assert np.abs(data.Fu - numeric_data.Fu).max() < 1e-5 * scale_u
    assert np.abs(data.Lx - numeric_data.Lx).max() < 1e-4 * np.abs(numeric_data.Lx).max()
    # A wrong base block (the identity instead of Ad(exp(-dx))) is far outside that tolerance.
    wrong = np.array(data.Fx)
    wrong[:6, :6] = np.eye(6)
    assert np.abs(wrong - numeric_data.Fx).max() > 1e-3 * scale_x


def test_shared_data_is_allocated_once_and_only_when_asked(node):
    model, _, _ = node
    assert model.createData() is model.createData()  # the builder's nodes share: windows reuse it
    private = MatchedEulerModel(model.differential, model.dt, model.substeps)
    assert private.createData() is not private.createData()
    with pytest.raises(ValueError, match="substeps"):
        MatchedEulerModel(model.differential, 0.03, 0)


def test_a_dropped_data_is_freed(node):
    """A data that held views of its own arrays was never collected: 1.7 MB per node, 9.7 GB after 12 walks."""
    model, x, u = node
    private = MatchedEulerModel(model.differential, model.dt, model.substeps)
    data = private.createData()
    private.calc(data, x, u)
    private.calcDiff(data, x, u)
    ref = weakref.ref(data)
    del data
    gc.collect()
    assert ref() is None
