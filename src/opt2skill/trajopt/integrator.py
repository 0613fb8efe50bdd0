"""A coarse-grid step that lands where the 200 Hz frames will: semi-implicit Euler matched to substeps.

The frames of a solved motion are a 5-ms semi-implicit Euler rollout of the optimizer's own contact
dynamics (`trajopt.frames`). Over one coarse node of `dt = N * 5 ms` with the torque held and the
acceleration a roughly constant, those N steps give

    v' = v + a dt,    q' = q (+) (v dt + a dt^2 (N + 1) / (2 N)),

while Crocoddyl's semi-implicit Euler at `dt` moves the configuration by `v dt + a dt^2`. With the
swing-leg accelerations of fast walking (150 to 200 rad/s^2 at the knee) the difference is 0.05 to
0.1 rad per 30-ms node: the frames cannot follow such a plan, their feedback fights the gap and the
cone limits of the rollout make it drift (docs/trajopt.md). This model uses the matched position
update at the same cost as Euler (one evaluation of the dynamics): velocities still follow
`v' = v + a dt`, so the record's inverse-dynamics convention on the knots is unchanged.

Crocoddyl's C++ integrators have no such option. `matched_euler` builds the compiled model where it
compiles (`trajopt.native`: Crocoddyl's Euler with its position factor set to the matched one), and
otherwise `MatchedEulerModel` below, a Python action model around the C++ differential model; the
two agree to round-off (tests/test_trajopt_native.py). The Python model's part is the integration
and the chain rule, written on views of the data's arrays (taken once) with the floating base's 6x6
blocks from Pinocchio: about 5 us more per `calc` and 20 to 40 us more per `calcDiff` than the
compiled one (docs/trajopt.md), where its first version, through `Jintegrate` and attribute copies,
added 100 to 130 us.
"""

from __future__ import annotations

import crocoddyl
import numpy as np
import pinocchio as pin

from opt2skill.trajopt.native import load as load_native


def matched_euler(differential, dt: float, substeps: int):
    """The matched integrator over `differential`: the compiled model, or the Python one sharing its
    data across the problems built on it (the receding windows)."""
    native = load_native()
    if native is not None:
        return native.MatchedEulerModel(differential, float(dt), int(substeps))
    return MatchedEulerModel(differential, dt, substeps, share_data=True)


def share_scratch(model, scratch: dict, key: tuple) -> None:
    """Let a compiled matched node evaluate its differential model in one data shared by every node
    built with the same `key` (kept in `scratch`), so a window's node loop runs in cache (docs/trajopt.md,
    "The node loop is memory-bound"). The key must name what the data's layout depends on besides the
    contacts and costs (`structure` adds those): the state and the actuation. A problem over such nodes
    must run its node loop on one thread (`single_threaded`, as every problem here does): two threads
    would evaluate two nodes in one scratch. The Python model keeps its own data."""
    if not hasattr(model, "share_differential_data"):
        return
    key = (key, structure(model.differential))
    if key not in scratch:
        scratch[key] = model.differential.createData()
    model.share_differential_data(scratch[key])


def structure(differential) -> tuple:
    """What a contact-dynamics data's layout depends on in its contacts and costs: each by name,
    kind, size and the frame it refers to, and whether it is active."""
    contacts = tuple(
        (name, type(item.contact).__name__, item.contact.id, item.contact.nc, item.active)
        for name, item in differential.contacts.contacts.todict().items()
    )
    costs = tuple(
        (name, type(item.cost).__name__, type(item.cost.residual).__name__, item.cost.residual.nr,
         getattr(item.cost.residual, "id", None), type(item.cost.activation).__name__, item.active)
        for name, item in differential.costs.costs.todict().items()
    )
    return contacts, costs


def compiled(model) -> bool:
    """Whether a node model is Crocoddyl C++ (its datas can be handed to a new problem); the Python
    model's data is refused there (`checkData` cannot be overridden from Python)."""
    return not isinstance(model, MatchedEulerModel)


def single_threaded(problem):
    """`problem` with its node loop on the calling thread. With only compiled nodes Crocoddyl runs
    it on an OpenMP team of every core, whatever OMP_NUM_THREADS says; `generate` already runs one
    worker per core, and two teams on two cores slow each other down; a Python part inside a C++
    node (the squeeze's actuation) must not run on a thread without the GIL either. With a Python
    node in it, Crocoddyl keeps one thread by itself (and warns if asked for another number)."""
    if problem.nthreads != 1:
        problem.nthreads = 1
    return problem


def implementation() -> str:
    """'compiled' or 'python': which matched integrator `matched_euler` builds in this process."""
    return "compiled" if load_native() is not None else "python"


class MatchedEulerModel(crocoddyl.ActionModelAbstract):
    """Integrated action model: `differential` over `dt`, position update matched to `substeps` Euler steps."""

    def __init__(self, differential, dt: float, substeps: int, share_data: bool = False):
        if dt <= 0 or substeps < 1:
            raise ValueError(f"MatchedEulerModel needs dt > 0 and substeps >= 1, got {dt}, {substeps}")
        joints = differential.state.pinocchio.joints
        if len(joints) < 2 or joints[1].shortname() != "JointModelFreeFlyer":
            raise ValueError("MatchedEulerModel is written for a floating-base robot (a free flyer as first joint)")
        crocoddyl.ActionModelAbstract.__init__(self, differential.state, differential.nu, differential.nr)
        self.differential = differential
        self.dt = float(dt)
        self.substeps = int(substeps)
        self.position_dt2 = self.dt**2 * (substeps + 1) / (2 * substeps)  # 1 * dt^2 for one substep (Euler)
        self.nv = differential.state.nv
        self.u_lb = differential.u_lb
        self.u_ub = differential.u_ub
        self.share_data = share_data
        self._data = None

    def calc(self, data, x, u=None):
        dd = data.differential
        if u is None:  # evaluated as a terminal node: cost only, no step (as Crocoddyl's integrators)
            self.differential.calc(dd, x)
            data.xnext[:] = x
            data.cost = dd.cost
            return
        self.differential.calc(dd, x, u)
        nv, dx, a = self.nv, data.dx, data.a
        np.multiply(a, self.position_dt2, out=dx[:nv])
        dx[:nv] += self.dt * x[-nv:]
        np.multiply(a, self.dt, out=dx[nv:])
        data.xnext[:] = self.state.integrate(x, dx)
        data.cost = self.dt * dd.cost

    def calcDiff(self, data, x, u=None):
        dd = data.differential
        if u is None:
            self.differential.calcDiff(dd, x)
            data.Fx[:] = np.eye(2 * self.nv)
            data.Lx[:], data.Lxx[:] = dd.Lx, dd.Lxx
            return
        self.differential.calcDiff(dd, x, u)
        nv, dt, c = self.nv, self.dt, self.position_dt2
        # x' = x (+) dx, dx = [v dt + c a, a dt]. The state's integration is the identity except for
        # the floating base: q_b' = q_b exp6(dx_b), so d q_b'/d q_b = Ad(exp6(-dx_b)) and
        # d q_b'/d dx_b = Jexp6(dx_b) (Crocoddyl's Jintegrate; tests/test_trajopt_integrator.py).
        base = data.dx[:6]
        by_base = pin.Jexp6(base)
        fx, fu = data.Fx, data.Fu
        position, velocity = fx[:nv], fx[nv:]
        np.multiply(data.da_dx, c, out=position)  # d(dx_q)/dx = c da/dx + [0, dt I]
        position[:, nv:] += data.dt_eye
        position[:6] = by_base @ position[:6]
        position[:6, :6] += pin.exp6(-base).action
        position[6:, 6:nv] += data.eye_joints
        np.multiply(data.da_dx, dt, out=velocity)
        velocity[:, nv:] += data.eye
        np.multiply(data.da_du, c, out=fu[:nv])
        fu[:6] = by_base @ fu[:6]
        np.multiply(data.da_du, dt, out=fu[nv:])
        for name, theirs in data.cost_derivatives:
            np.multiply(theirs, dt, out=getattr(data, name))

    def quasiStatic(self, data, x, maxiter: int = 100, tol: float = 1e-9):
        return self.differential.quasiStatic(data.differential, x, maxiter, tol)

    def createData(self):
        """A new data, or with `share_data` the model's one data, allocated at the first call.

        A node's model belongs to one problem at a time (the whole motion, then each receding
        window in turn), and every problem built on it allocates its data: about 2.5 ms for a
        contact-dynamics node, about 3 s for the 1334 window nodes of a 14-s walk (shared
        machine). Crocoddyl's constructor that takes existing datas cannot be used with a Python
        model (it rejects their data: `checkData` is not overridable from Python), hence this.
        """
        if not self.share_data:
            return MatchedEulerData(self)
        if self._data is None:
            self._data = MatchedEulerData(self)
        return self._data


class MatchedEulerData(crocoddyl.ActionDataAbstract):
    """The data plus numpy views of the differential data's arrays (taken once: each attribute read
    through the bindings costs microseconds). Views of this data's own arrays are not kept: a view
    refers to its owner, and that cycle through a numpy array is never collected (1.7 MB leaked
    per node data)."""

    def __init__(self, model: MatchedEulerModel):
        crocoddyl.ActionDataAbstract.__init__(self, model)
        nv = model.nv
        self.differential = model.differential.createData()
        dd = self.differential
        self.dx = np.zeros(2 * nv)
        self.a, self.da_dx, self.da_du = dd.xout, dd.Fx, dd.Fu
        self.cost_derivatives = [(n, getattr(dd, n)) for n in ("Lx", "Lu", "Lxx", "Lxu", "Luu")]
        self.eye = np.eye(nv)
        self.eye_joints = np.eye(nv - 6)
        self.dt_eye = model.dt * self.eye
