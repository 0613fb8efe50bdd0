"""The compiled parts of the optimizer (trajopt.native): they build where a C++ compiler is; the
matched integrator is the Python model's step and derivatives to round-off, the barrier cost is
Crocoddyl's residual cost to the bit; the optimizer uses both, and a failed build is one clear
reason with the Python model and Crocoddyl's costs taking over."""

import os
import subprocess
import sys
import tempfile

import crocoddyl
import numpy as np
import pytest

from opt2skill.model import load_robot
from opt2skill.tasks import get_task
from opt2skill.trajopt import costs, integrator, native
from opt2skill.trajopt.integrator import MatchedEulerModel

# Where the build's prerequisites are all here (as in CI), a missing module is a failure, not a skip.
needs_compiler = pytest.mark.skipif(native.missing_prerequisite() is not None,
                                    reason=f"cannot build here: {native.missing_prerequisite()}")


@pytest.fixture(scope="module")
def walk():
    robot = load_robot("digit")
    task = get_task("walk", robot, {"steps": 2, "duration": 1.5})
    plan = task.plan(task.param_space().sample(0, 3))
    problem = task.builder.build(task._with_standard_costs(plan), plan.x0, 0.03, integrator="matched")
    return task, plan, problem


def random_state(plan, seed: int):
    rng = np.random.default_rng(seed)
    x = plan.x0.copy()
    q = np.array([0.05, -0.03, 0.2, 1.0]) + rng.normal(scale=0.05, size=4)
    x[3:7] = q / np.linalg.norm(q)  # a turned, tilted base: the floating base's blocks matter
    x[7:27] += rng.normal(scale=0.1, size=20)
    x[27:] = rng.normal(scale=0.8, size=26)
    return x, rng.normal(scale=20.0, size=20)


@needs_compiler
def test_it_builds_here_and_the_optimizer_uses_it(walk):
    assert native.load() is not None, native.unavailable_reason()
    assert integrator.implementation() == "compiled"
    _, _, problem = walk
    running = [m for m, n in zip(problem.shooting.runningModels, problem.nodes) if n.kind == "running"]
    compiled = [m for m in running if isinstance(m, native.load().MatchedEulerModel)]
    assert len(compiled) == len(running) > 20
    cones = [item.cost for m in running for name, item in m.differential.costs.costs.todict().items()
             if name.endswith("_cone")]
    assert len(cones) > len(running) and all(isinstance(c, native.load().BarrierCostModel) for c in cones)
    assert problem.shooting.nthreads == 1  # one worker per core: no OpenMP team inside a problem


@needs_compiler
@pytest.mark.parametrize("contacts", [1, 2])
def test_step_and_derivatives_are_the_python_models(walk, contacts):
    _, plan, problem = walk
    k = next(i for i, n in enumerate(problem.nodes) if n.kind == "running" and len(n.contacts) == contacts)
    built = problem.shooting.runningModels[k]
    fast = native.load().MatchedEulerModel(built.differential, built.dt, built.substeps)
    slow = MatchedEulerModel(built.differential, built.dt, built.substeps)
    assert fast.substeps == slow.substeps >= 5 and fast.position_dt2 == pytest.approx(slow.position_dt2, rel=1e-15)
    np.testing.assert_array_equal(fast.u_lb, slow.u_lb)
    fd, sd = fast.createData(), slow.createData()
    for seed in range(3):
        x, u = random_state(plan, seed)
        for model, data in ((fast, fd), (slow, sd)):
            model.calc(data, x, u)
            model.calcDiff(data, x, u)
        for name in ("xnext", "Fx", "Fu", "Lx", "Lu", "Lxx", "Lxu", "Luu"):
            mine, theirs = np.asarray(getattr(fd, name)), np.asarray(getattr(sd, name))
            assert np.abs(mine - theirs).max() <= 1e-12 * max(1.0, np.abs(theirs).max()), name
        assert fd.cost == pytest.approx(sd.cost, rel=1e-14)
    # Crocoddyl's own Euler differs from both: the position factor is really changed.
    euler = crocoddyl.IntegratedActionModelEuler(built.differential, built.dt)
    ed = euler.createData()
    euler.calc(ed, x, u)
    assert np.abs(np.asarray(ed.xnext)[7:27] - np.asarray(fd.xnext)[7:27]).max() > 1e-4
    with pytest.raises(ValueError, match="substeps >= 1, got 0.03"):
        native.load().MatchedEulerModel(built.differential, built.dt, 0)
    with pytest.raises(ValueError, match="needs a differential action model"):  # not a crash in C++
        native.load().MatchedEulerModel(None, built.dt, 6)
    with pytest.raises(AttributeError):  # Crocoddyl's dt setter would silently make it plain Euler
        fast.dt = 0.02
    assert fast.dt == built.dt and fast.position_dt2 == pytest.approx(slow.position_dt2, rel=1e-15)


def _barriers(model, data) -> list[tuple[int, int]]:
    """(active rows, rows) of each of the node's barrier costs: rows whose residual is on or outside
    its bounds."""
    out = []
    for name, item in data.differential.costs.costs.todict().items():
        activation = model.differential.costs.costs[name].cost.activation
        if isinstance(activation, crocoddyl.ActivationModelQuadraticBarrier):
            r, bounds = np.asarray(item.residual.r), activation.bounds
            out.append((int(np.sum((r <= bounds.lb) | (r >= bounds.ub))), len(r)))
    return out


@needs_compiler
@pytest.mark.parametrize("contacts", [1, 2])
def test_barrier_costs_give_crocoddyls_derivatives(walk, monkeypatch, contacts):
    """Each node built with the compiled barrier costs and with Crocoddyl's: the same cost and
    derivatives exactly where every barrier is flat, to round-off where a few rows are active (the
    products over those rows alone) or many (Crocoddyl's products), states far off the plan; and on one
    data reused from active states to a flat one (the skipped derivatives are zero, not stale)."""
    task, plan, fast_problem = walk
    monkeypatch.setattr(costs, "load_native", lambda: None)
    slow_problem = task.builder.build(task._with_standard_costs(plan), plan.x0, 0.03, integrator="matched")
    k = next(i for i, n in enumerate(fast_problem.nodes) if n.kind == "running" and len(n.contacts) == contacts)
    fast, slow = fast_problem.shooting.runningModels[k], slow_problem.shooting.runningModels[k]
    barrier = native.load().BarrierCostModel
    kinds = {name: type(item.cost) for name, item in fast.differential.costs.costs.todict().items()}
    assert sum(kind is barrier for kind in kinds.values()) == contacts + 1  # the cones and the joint limits
    assert not any(isinstance(item.cost, barrier) for item in slow.differential.costs.costs.todict().values())
    standing = (plan.x0, np.zeros(fast.nu))
    states = [random_state(plan, seed) for seed in range(3)] + [standing]
    fd = fast.createData()  # one data through every state, as in a solve
    seen = []
    for x, u in states:
        sd = slow.createData()
        for model, data in ((fast, fd), (slow, sd)):
            model.calc(data, x, u)
            model.calcDiff(data, x, u)
        seen += (barriers := _barriers(fast, fd))
        for name in ("Lx", "Lu", "Lxx", "Lxu", "Luu", "Fx", "Fu"):
            mine, crocoddyls = np.asarray(getattr(fd, name)), np.asarray(getattr(sd, name))
            if not any(active for active, _ in barriers):
                np.testing.assert_array_equal(mine, crocoddyls, err_msg=name)
            else:  # another order of the same sums: 6e-16 seen; a dropped row or block is off by far more
                scale = max(1.0, float(np.abs(crocoddyls).max()))
                assert np.abs(mine - crocoddyls).max() <= 1e-13 * scale, (name, np.abs(mine - crocoddyls).max(), scale)
        assert fd.cost == sd.cost
    assert any(0 < active < rows / 2 for active, rows in seen)  # products over a few rows
    assert any(active >= rows / 2 for active, rows in seen)  # and Crocoddyl's, where most rows are active
    assert not any(active for active, _ in seen[-(contacts + 1):])  # skipped at the end, on the same data
    with pytest.raises(ValueError, match="needs a state, an activation and a residual"):  # not a crash in C++
        barrier(None, crocoddyl.ActivationModelQuad(3), None)


@needs_compiler
def test_a_walk_solves_to_the_same_plan_with_either(walk, monkeypatch):
    """Two receding windows of a real walk, solved with each implementation: the same iterations
    and the same plan to round-off; with Crocoddyl's barrier costs instead of the compiled ones, the
    same again."""
    task, plan, _ = walk
    from opt2skill.trajopt import phases, solver
    from opt2skill.trajopt.receding import solve_receding
    from opt2skill.trajopt.skills.stride_guess import StrideGuess

    # Crocoddyl's own backward pass and contact dynamics, so that only the integrator differs (FMA's
    # round-off in the parts compiled for AVX2 grows through the gap-closing windows to 1e-5 of the cost:
    # their own test below).
    monkeypatch.setattr(solver, "load_native", lambda: None)
    monkeypatch.setattr(phases, "load_native", lambda: None)

    def solve():
        phases = task._with_standard_costs(plan)
        problem = task.builder.build(phases, plan.x0, 0.03, integrator="matched")
        return solve_receding(problem, task.config.solver, window=0.6, commit=0.3, max_iter=6,
                              first_max_iter=10, extend=StrideGuess(problem, plan.context))

    fast = solve()
    with monkeypatch.context() as patch:
        patch.setattr(costs, "load_native", lambda: None)
        crocoddyl_barriers = solve()
    # The active barriers' products over their active rows are another order of Crocoddyl's sums (1e-16
    # per node); through the gap-closing windows that grew to 1e-7 of the cost here.
    assert crocoddyl_barriers.iterations == fast.iterations
    assert crocoddyl_barriers.cost == pytest.approx(fast.cost, rel=1e-6)
    assert np.abs(crocoddyl_barriers.xs - fast.xs).max() < 1e-4
    for mine, theirs in zip(crocoddyl_barriers.us, fast.us, strict=True):  # impulse nodes have no torque
        assert np.allclose(mine, theirs, rtol=0.0, atol=1e-2)  # N m, of torques up to hundreds
    monkeypatch.setattr(integrator, "load_native", lambda: None)
    assert integrator.implementation() == "python"
    slow = solve()
    assert fast.iterations == slow.iterations > 10
    # Round-off grows through the iterations (2e-6 seen here); a wrong integrator moves a node by 1e-4 or more.
    assert np.abs(fast.xs - slow.xs).max() < 1e-4
    assert fast.cost == pytest.approx(slow.cost, rel=1e-6)


@needs_compiler
def test_nodes_sharing_a_scratch_solve_to_the_same_plan_to_the_bit(walk, monkeypatch):
    """The compiled matched nodes of one structure evaluate their contact dynamics and costs in one
    shared data (the node loop then runs in cache): the same receding solve, the same knots (their
    contact forces read node by node, each just evaluated) and the same gains as with a data per node."""
    task, plan, _ = walk
    from opt2skill.trajopt import phases
    from opt2skill.trajopt.extract import knots
    from opt2skill.trajopt.frames import interpolate
    from opt2skill.trajopt.receding import solve_receding
    from opt2skill.trajopt.skills.stride_guess import StrideGuess
    from opt2skill.trajopt.solver import riccati_gains

    problem = task.builder.build(task._with_standard_costs(plan), plan.x0, 0.03, integrator="matched")
    running = [m for m in problem.shooting.runningModels if isinstance(m, native.load().MatchedEulerModel)]
    assert running and all(m.shares_data for m in running)
    assert 2 <= len(task.builder._scratch) < len(running) / 4  # a few structures: stance, each swing, ...
    # each node's data is made with a scratch as its differential data: a mark written into each scratch
    # reads back through every node's data, and every scratch is some node's
    for mark, scratch in enumerate(task.builder._scratch.values()):
        scratch.cost = 1000.0 + mark
    marks = {d.differential.cost for m, d in zip(problem.shooting.runningModels, problem.shooting.runningDatas)
             if isinstance(m, native.load().MatchedEulerModel)}
    assert marks == {1000.0 + mark for mark in range(len(task.builder._scratch))}

    def solve():
        built = task.builder.build(task._with_standard_costs(plan), plan.x0, 0.03, integrator="matched")
        sol = solve_receding(built, task.config.solver, window=0.6, commit=0.3, max_iter=6, first_max_iter=10,
                             extend=StrideGuess(built, plan.context))
        return (sol, knots(built, sol, keep_gains=False), riccati_gains(built.shooting, sol.xs, sol.us, 1e-6),
                interpolate(built, sol).wrench)

    shared, shared_knots, shared_gains, shared_wrench = solve()
    monkeypatch.setattr(phases, "share_scratch", lambda *args: None)
    own, own_knots, own_gains, own_wrench = solve()
    np.testing.assert_array_equal(shared_wrench, own_wrench)  # the interpolated frames' held forces too
    assert not any(m.shares_data for m in task.builder.build(task._with_standard_costs(plan), plan.x0, 0.03,
                                                             integrator="matched").shooting.runningModels
                   if isinstance(m, native.load().MatchedEulerModel))
    assert shared.iterations == own.iterations > 10 and shared.cost == own.cost
    np.testing.assert_array_equal(shared.xs, own.xs)
    assert np.abs(shared_knots["contact_force"]).max() > 100.0  # the feet carry the robot
    for key in own_knots:
        np.testing.assert_array_equal(shared_knots[key], own_knots[key])
    for mine, theirs in zip(shared_gains, own_gains, strict=True):
        np.testing.assert_array_equal(mine, theirs)


@needs_compiler
def test_a_scratch_of_another_kind_of_model_is_refused(walk):
    _, _, problem = walk
    node = next(m for m in problem.shooting.runningModels if isinstance(m, native.load().MatchedEulerModel))
    state = node.differential.state
    free = crocoddyl.DifferentialActionModelFreeFwdDynamics(
        state, crocoddyl.ActuationModelFloatingBase(state), crocoddyl.CostModelSum(state, node.nu))
    with pytest.raises(ValueError, match="kind of differential model"):
        node.share_differential_data(free.createData())


def test_a_failed_build_is_one_reason_and_the_python_model_takes_over(tmp_path):
    """No compiler: `load()` gives None with the reason, `python -m opt2skill.trajopt.native` exits 1
    with one line naming it, and the optimizer builds the Python model."""
    env = {**os.environ, "OPT2SKILL_CACHE": str(tmp_path), "CXX": str(tmp_path / "no-such-compiler")}
    code = ("from opt2skill.trajopt import native, integrator\n"
            "assert native.load() is None\n"
            "print(native.unavailable_reason())\n"
            "print(integrator.implementation())")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    reason, used = out.stdout.strip().splitlines()
    assert "no C++ compiler" in reason and "no-such-compiler" in reason and used == "python"
    assert out.stderr.count("using the Python matched integrator") == 1  # logged once, as a warning
    cli = subprocess.run([sys.executable, "-m", "opt2skill.trajopt.native"], env=env, capture_output=True,
                         text=True, timeout=120)
    assert cli.returncode == 1
    assert cli.stderr.count("\n") == 1 and "no C++ compiler" in cli.stderr
    assert not list(tmp_path.rglob("*.so"))  # nothing half-built is left to be loaded later


def test_it_can_be_turned_off(tmp_path):
    env = {**os.environ, "OPT2SKILL_NATIVE": "0"}
    code = "from opt2skill.trajopt import integrator, native\nprint(integrator.implementation(), native.unavailable_reason())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "python disabled by OPT2SKILL_NATIVE=0"


@needs_compiler
def test_a_build_is_kept_per_source_and_stack(tmp_path, monkeypatch):
    """The build is cached under a key of the source and the stack's versions; a compile error
    names the file and keeps nothing."""
    monkeypatch.setenv("OPT2SKILL_CACHE", str(tmp_path))
    first = native.build()
    stamp = first.stat().st_mtime_ns
    assert native.build() == first and first.stat().st_mtime_ns == stamp  # not compiled again
    assert native.build_key() in str(first)
    broken = tmp_path / "broken.cpp"
    broken.write_text("this is not C++\n")
    monkeypatch.setattr(native, "SOURCE", broken)
    assert native.build_key() not in str(first)
    with pytest.raises(native.NativeBuildError, match="compiling broken.cpp failed"):
        native.build()
    assert list(tmp_path.rglob("*.so")) == [first]


@needs_compiler
def test_a_damaged_build_in_the_cache_is_built_again(tmp_path):
    env = {**os.environ, "OPT2SKILL_CACHE": str(tmp_path)}
    code = "from opt2skill.trajopt import native\nprint(native.build())"
    path = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert path.returncode == 0, path.stderr
    so = tmp_path / path.stdout.strip()
    so.write_bytes(b"not a shared object")  # what a copy killed halfway would leave
    use = "from opt2skill.trajopt import integrator\nprint(integrator.implementation())"
    out = subprocess.run([sys.executable, "-c", use], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "compiled", out.stderr
    assert so.read_bytes()[:4] == b"\x7fELF"


@needs_compiler
def test_an_unwritable_cache_builds_in_the_temporary_folder(tmp_path, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv("OPT2SKILL_CACHE", str(blocker / "cache"))  # under a file: cannot be created
    path = native.build()
    assert path.exists() and path.is_relative_to(tempfile.gettempdir()) and not path.is_relative_to(blocker)


@needs_compiler
def test_the_frames_tracking_loop_gives_the_python_frames(walk, monkeypatch):
    """The 200 Hz frames' tracking law run in C++ (`track_frames`, frames whose wrenches leave their
    cones projected in Python) gives the Python loop's frames to round-off, projections included."""
    task, plan, _ = walk
    from opt2skill.trajopt import frames
    from opt2skill.trajopt.receding import solve_receding
    from opt2skill.trajopt.skills.stride_guess import StrideGuess
    from opt2skill.trajopt.tracking import track

    def problem():  # completing frames moves a problem's touchdown references: one problem each way
        return task.builder.build(task._with_standard_costs(plan), plan.x0, 0.03, integrator="matched")

    solved = problem()
    solution = solve_receding(solved, task.config.solver, window=0.6, commit=0.3, max_iter=6, first_max_iter=10,
                              extend=StrideGuess(solved, plan.context))
    projections = []
    project = frames.ContactCones.project
    monkeypatch.setattr(frames.ContactCones, "project", lambda *a, **k: projections.append(1) or project(*a, **k))
    compiled_nodes = []
    compiled_node = frames._compiled_node
    monkeypatch.setattr(frames, "_compiled_node", lambda *a: compiled_nodes.append(1) or compiled_node(*a))
    compiled_problem = problem()
    fast = track(compiled_problem, solution, task._cones(compiled_problem), task.config.solver.track_bandwidth)
    compiled_projections = len(projections)
    monkeypatch.setattr(frames, "load_native", lambda: None)
    python_problem = problem()
    slow = track(python_problem, solution, task._cones(python_problem), task.config.solver.track_bandwidth)
    assert compiled_projections == len(projections) - compiled_projections > 0  # the same frames projected
    assert len(compiled_nodes) == sum(n.kind == "running" for n in python_problem.nodes[:-1])
    assert len(slow.q) == int(round(python_problem.duration / 0.005)) + 1
    np.testing.assert_array_equal(fast.active, slow.active)
    # Round-off through the feedback (gain @ error summed in another order): 1e-12 rad seen on a 14-s walk.
    np.testing.assert_allclose(fast.q, slow.q, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast.v, slow.v, rtol=0, atol=1e-7)
    np.testing.assert_allclose(fast.tau, slow.tau, rtol=0, atol=1e-5)
    np.testing.assert_allclose(fast.wrench, slow.wrench, rtol=0, atol=1e-5)
    assert np.abs(slow.wrench).max() > 100.0 and np.abs(slow.tau).max() > 10.0


@needs_compiler
def test_the_parts_compiled_for_avx2_give_crocoddyls_plans(walk, monkeypatch):
    """Box-FDDP's backward pass and the contact dynamics' derivatives compiled for AVX2 and FMA (where
    this CPU has them, as every machine of the project's) solve two receding windows of a real walk in
    Crocoddyl's iterations, to its plan within round-off, and give its feedback gains."""
    needs_simd()
    task, plan, _ = walk
    from opt2skill.trajopt import phases, solver
    from opt2skill.trajopt.receding import solve_receding
    from opt2skill.trajopt.skills.stride_guess import StrideGuess

    made = []  # the solvers of the windows
    box_fddp = solver.box_fddp

    def recorded(shooting):
        made.append(box_fddp(shooting))
        return made[-1]

    monkeypatch.setattr(solver, "box_fddp", recorded)

    def solve():
        made.clear()
        built = task.builder.build(task._with_standard_costs(plan), plan.x0, 0.03, integrator="matched")
        sol = solve_receding(built, task.config.solver, window=0.6, commit=0.3, max_iter=6, first_max_iter=10,
                             extend=StrideGuess(built, plan.context))
        windows = list(made)
        return sol, solver.riccati_gains(built.shooting, sol.xs, sol.us, 1e-6), windows

    compiled, compiled_gains, windows = solve()
    assert isinstance(windows[0], native.load_simd().BoxFDDP) and solver.solver_implementation() == "avx2-fma"
    # Line-search trials stop once they cannot be accepted: here about a third of them, a fifth of their
    # nodes left out, and every iteration still takes Crocoddyl's step length (below).
    stopped = sum(w.line_search_stopped for w in windows)
    skipped = sum(w.line_search_nodes_skipped for w in windows)
    assert stopped > 0.1 * sum(w.line_search_trials for w in windows)
    assert skipped > 0.05 * (skipped + sum(w.line_search_nodes for w in windows))
    monkeypatch.setattr(solver, "load_native", lambda: None)
    monkeypatch.setattr(phases, "load_native", lambda: None)
    theirs, their_gains, windows = solve()
    assert type(windows[0]) is crocoddyl.SolverBoxFDDP and solver.solver_implementation() == "crocoddyl"
    assert compiled.iterations == theirs.iterations > 10
    assert [w[1] for w in compiled.windows] == [w[1] for w in theirs.windows]  # iterations per window
    # FMA rounds differently: 3e-6 in the states, 2e-6 of the cost and 4e-6 of the gains seen here (6e-6,
    # 8e-6 and 2e-6 with the backward pass alone; the windows close gaps, where round-off grows). Without
    # the gaps' term of the value function: 12, 150 times, 16.
    assert np.abs(compiled.xs - theirs.xs).max() < 1e-3
    assert compiled.cost == pytest.approx(theirs.cost, rel=1e-4)
    for mine, crocoddyls in zip(compiled_gains, their_gains, strict=True):
        assert mine.shape == crocoddyls.shape
        if crocoddyls.size:  # an impulse node's gain is empty
            np.testing.assert_allclose(mine, crocoddyls, rtol=0, atol=1e-4 * max(1.0, np.abs(crocoddyls).max()))
    assert max(np.abs(k).max() for k in their_gains if k.size) > 10.0  # real gains, not zeros


class _Wavy(crocoddyl.ActionModelAbstract):
    """x' = x + sin(3 u), cost (x - 2)^2 + 0.01 u^2 + offset: nonlinear enough for many rejected
    line-search trials; a negative offset makes every node's cost negative."""

    def __init__(self, offset: float, terminal: bool = False):
        super().__init__(crocoddyl.StateVector(1), 1, 1)
        self.offset, self.terminal = offset, terminal

    def calc(self, data, x, u=None):
        u = np.zeros(1) if u is None or self.terminal else u
        data.xnext = x + np.sin(3.0 * u)
        data.cost = float((x[0] - 2.0) ** 2 + 0.01 * u[0] ** 2 + self.offset)

    def calcDiff(self, data, x, u=None):
        u = np.zeros(1) if u is None or self.terminal else u
        data.Fx, data.Fu = np.eye(1), np.array([[3.0 * np.cos(3.0 * u[0])]])
        data.Lx, data.Lxx = np.array([2.0 * (x[0] - 2.0)]), np.array([[2.0]])
        data.Lu, data.Luu, data.Lxu = np.array([0.02 * u[0]]), np.array([[0.02]]), np.zeros((1, 1))


@needs_compiler
@pytest.mark.parametrize("u0", [0.0, 0.5])
def test_the_line_search_stops_only_where_costs_are_not_negative(u0):
    """The compiled Box-FDDP's early stop of a line-search trial needs every node's cost >= 0: on a
    small nonlinear problem it stops most rejected trials and keeps Crocoddyl's iterates exactly; with
    every cost shifted below zero it stops none (a partial sum no longer bounds the total) and still
    gives Crocoddyl's iterates."""
    needs_simd()

    def solve(offset, solver_class):
        problem = crocoddyl.ShootingProblem(np.array([0.0]), [_Wavy(offset) for _ in range(20)], _Wavy(offset, True))
        xs = [np.array([0.0])]
        for _ in range(20):  # a rollout: the guess has no gaps
            xs.append(xs[-1] + np.sin(3.0 * np.array([u0])))
        solver = solver_class(problem)
        solver.solve(xs, [np.array([u0])] * 20, 60, True, 1e-9)
        return solver

    for offset in (0.0, -50.0):
        mine, crocoddyls = solve(offset, native.load_simd().BoxFDDP), solve(offset, crocoddyl.SolverBoxFDDP)
        assert mine.iter == crocoddyls.iter > 20
        np.testing.assert_allclose(np.array(mine.xs), np.array(crocoddyls.xs), rtol=0, atol=1e-12)
        if offset == 0.0:
            assert mine.line_search_stopped > 0.5 * mine.line_search_trials
        else:
            assert mine.line_search_stopped == 0 and mine.line_search_trials > 100


def needs_simd():
    if native.load_simd() is None:
        if native.load().cpu_has_avx2_fma():  # it must build wherever it can run
            pytest.fail(native.simd_unavailable_reason())
        pytest.skip(native.simd_unavailable_reason())


@needs_compiler
@pytest.mark.parametrize("contacts", [1, 2])
def test_the_contact_dynamics_derivatives_compiled_for_avx2_are_crocoddyls(walk, contacts):
    """A node's contact dynamics with its derivatives' products compiled for AVX2 and FMA gives
    Crocoddyl's step, cost, derivatives and contact forces' derivatives to round-off, off the solution
    (a turned, tilted base, joints and speeds spread)."""
    needs_simd()
    _, plan, problem = walk
    node = next(m for m in problem.shooting.runningModels if m.differential.contacts.nc == 6 * contacts)
    ours = node.differential
    assert isinstance(ours, native.load_simd().ContactFwdDynamics)
    theirs = crocoddyl.DifferentialActionModelContactFwdDynamics(ours.state, ours.actuation, ours.contacts,
                                                                  ours.costs, 0.0, True)
    for seed in range(3):
        x, u = random_state(plan, seed)
        mine, crocoddyls = ours.createData(), theirs.createData()
        for model, data in ((ours, mine), (theirs, crocoddyls)):
            model.calc(data, x, u)
            model.calcDiff(data, x, u)
        for name in ("xout", "Fx", "Fu", "Lx", "Lu", "Lxx", "Lxu", "Luu", "df_dx", "df_du"):
            a, b = getattr(mine, name), getattr(crocoddyls, name)
            scale = max(1.0, float(np.abs(b).max()))
            assert np.abs(a - b).max() <= 1e-9 * scale, (name, np.abs(a - b).max(), scale)
        assert len(theirs.contacts.contacts.todict()) == contacts
        assert np.abs(crocoddyls.Fx).max() > 1.0 and np.abs(crocoddyls.df_dx).max() > 1.0  # real derivatives


@needs_compiler
@pytest.mark.parametrize("contacts", [1, 2])
def test_the_contact_dynamics_step_compiled_for_avx2_is_crocoddyls(walk, contacts):
    """The compiled `calc` forms only the terms of `computeAllTerms` that the dynamics, contacts and
    costs read (native/dynamics_terms.hpp): it gives Crocoddyl's step, cost, every residual, the contact
    forces and placements, and the terms themselves (mass matrix with the armature, bias forces, CoM
    Jacobian for the CoM cost's derivative) to round-off, off the solution."""
    needs_simd()
    _, plan, problem = walk
    node = next(m for m in problem.shooting.runningModels if m.differential.contacts.nc == 6 * contacts)
    ours = node.differential
    theirs = crocoddyl.DifferentialActionModelContactFwdDynamics(ours.state, ours.actuation, ours.contacts,
                                                                  ours.costs, 0.0, True)
    costs_read = set(ours.costs.costs.todict())
    assert {"com_path", "posture", "torque"} <= costs_read and any(name.endswith("_cone") for name in costs_read)

    def close(a, b, what):
        a, b = np.asarray(a), np.asarray(b)
        scale = max(1.0, float(np.abs(b).max()))
        assert a.shape == b.shape and np.abs(a - b).max() <= 1e-10 * scale, (what, np.abs(a - b).max(), scale)

    for seed in range(3):
        x, u = random_state(plan, seed)
        mine, crocoddyls = ours.createData(), theirs.createData()
        ours.calc(mine, x, u)
        theirs.calc(crocoddyls, x, u)
        close(mine.xout, crocoddyls.xout, "xout")
        close(mine.cost, crocoddyls.cost, "cost")
        for name, data in crocoddyls.costs.costs.todict().items():
            close(mine.costs.costs[name].residual.r, data.residual.r, name)
        for name, data in crocoddyls.multibody.contacts.contacts.todict().items():
            close(mine.multibody.contacts.contacts[name].f.vector, data.f.vector, f"{name} force")
            close(mine.multibody.contacts.contacts[name].pinocchio.oMf[data.frame].homogeneous,
                  data.pinocchio.oMf[data.frame].homogeneous, f"{name} placement")
        a, b = mine.pinocchio, crocoddyls.pinocchio
        close(np.triu(a.M), np.triu(b.M), "M")  # Pinocchio fills the upper triangle
        for name in ("nle", "Jcom", "J", "com", "hg", "lambda_c"):
            close(getattr(a, name) if name != "com" else a.com[0], getattr(b, name) if name != "com" else b.com[0], name)
        assert abs(crocoddyls.cost) > 1.0 and np.abs(crocoddyls.xout).max() > 1.0  # a real step


@needs_compiler
def test_a_failed_avx2_build_is_one_reason_and_crocoddyls_classes_take_over():
    """The module compiled for AVX2 failing to build (here: an option the compiler refuses) leaves the
    first module in use, one warning with the reason, Crocoddyl's solver and contact dynamics, and no
    half-built module in the cache."""
    code = ("from opt2skill.trajopt import native, phases, solver\n"
            "native.SIMD_FLAGS = native.SIMD_FLAGS + ('-fno-such-option-here',)\n"
            "assert native.load() is not None and native.load_simd() is None and phases.load_native() is None\n"
            "print(native.simd_unavailable_reason())\n"
            "print(solver.solver_implementation())\n"
            "print(sorted(p.name for p in native.build_folder(native._simd_extension()).iterdir()))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    reason, used, left = out.stdout.strip().splitlines()
    assert "compiling simd_module.cpp failed" in reason and "no-such-option" in reason
    assert used == "crocoddyl" and ".so" not in left
    assert out.stderr.count("compiled for AVX2/FMA are unavailable") == 1
    assert out.stderr.count("using Crocoddyl's") == 1
