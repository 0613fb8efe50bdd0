"""Per-world physical parameters (the randomized ones) and how they reach each world's MjModel.

Every value is a factor of the nominal robot (1 = nominal) or an index, and is applied to the
world's own MjModel copy from the stored nominal values, so repeated resets never compound.

- `mass_scale` (nbody): scales each link's mass and rotational inertia together (uniform density),
  then `mj_setConst` refreshes the quantities MuJoCo derives from them (subtree masses, the
  constraint solver's inverse weights and mean inertia), as if the model had been compiled so.
- `friction_scale`: scales the friction coefficients of every geom, robot and ground alike.
  MuJoCo takes the larger of the two geoms' coefficients in a contact, so scaling the ground alone
  would do nothing while the feet keep theirs.
- `gravity_scale`: scales `opt.gravity`.
- `kp_factor`, `kd_factor` (nu): scale each servo's Kp and Kd.
- `motor_strength` (nu): scales the whole motor, i.e. Kp, Kd and the torque limit together: the
  applied torque is `s * clip(Kp (q* - q) - Kd qd, +-limit)`. A motor with a different torque
  constant delivers `s` times the torque commanded, including at saturation, because the limit is
  enforced on the command (Digit's LLAPI limits are command limits). The torque sensors report the
  torque applied to the joint, `s` included.
- `delay` (seconds, applied rounded to whole physics steps), `terrain` (index into the
  simulator's terrains), `props` (index into the simulator's prop sets, `scene.slots`) and `lift` (whether a reset lifts the given state onto the terrain) are
  applied by the simulator itself, not through the model.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import mujoco
import numpy as np

from opt2skill.errors import ConfigError, ModelError

# Hard bounds on the factors: anything outside is a bug in the caller, not a randomization.
FACTOR_BOUNDS = {
    "mass_scale": (0.05, 20.0),
    "friction_scale": (0.0, 20.0),
    "gravity_scale": (0.0, 5.0),
    "kp_factor": (0.0, 10.0),
    "kd_factor": (0.0, 10.0),
    "motor_strength": (0.0, 10.0),
}


@dataclass
class WorldParams:
    """Physical parameters of k worlds. Build with `WorldParams.nominal(...)` and overwrite fields."""

    mass_scale: np.ndarray  # (k, nbody) factor on link mass and inertia; body 0 (the world) ignored
    friction_scale: np.ndarray  # (k,) factor on every geom's friction coefficients
    gravity_scale: np.ndarray  # (k,) factor on gravity
    kp_factor: np.ndarray  # (k, nu) factor on Kp
    kd_factor: np.ndarray  # (k, nu) factor on Kd
    motor_strength: np.ndarray  # (k, nu) factor on Kp, Kd and the torque limit together
    delay: np.ndarray  # (k,) action delay, seconds (applied rounded to whole physics steps)
    terrain: np.ndarray  # (k,) int, index into the simulator's terrains
    # (k,) bool: a reset lifts the given state onto the terrain (a state made on the flat floor);
    # False keeps its height (a state made on this very terrain, e.g. a reference on its stairs).
    lift: np.ndarray
    props: np.ndarray  # (k,) int, index into the simulator's prop sets (scene/slots.py)

    @classmethod
    def nominal(cls, k: int, nbody: int, nu: int) -> WorldParams:
        return cls(
            mass_scale=np.ones((k, nbody)),
            friction_scale=np.ones(k),
            gravity_scale=np.ones(k),
            kp_factor=np.ones((k, nu)),
            kd_factor=np.ones((k, nu)),
            motor_strength=np.ones((k, nu)),
            delay=np.zeros(k),
            terrain=np.zeros(k, dtype=int),
            lift=np.ones(k, dtype=bool),
            props=np.zeros(k, dtype=int),
        )

    def __len__(self) -> int:
        return len(self.friction_scale)

    def rows(self, index: np.ndarray) -> WorldParams:
        return WorldParams(**{f.name: getattr(self, f.name)[index].copy() for f in fields(self)})

    def assign(self, index: np.ndarray, other: WorldParams) -> None:
        for f in fields(self):
            getattr(self, f.name)[index] = getattr(other, f.name)

    def checked(self, k: int, nbody: int, nu: int, max_delay: float, nterrain: int, nprops: int = 1) -> WorldParams:
        """A copy with every field broadcast to its full shape; ConfigError names any bad value.

        Per-joint and per-body fields accept (k, n), (n,), (k, 1) or a scalar.
        """
        shapes = {"mass_scale": (k, nbody), "kp_factor": (k, nu), "kd_factor": (k, nu), "motor_strength": (k, nu)}
        out = {}
        for f in fields(self):
            value = np.asarray(getattr(self, f.name))
            shape = shapes.get(f.name, (k,))
            try:
                value = np.broadcast_to(value, shape).copy()
            except ValueError:
                raise ConfigError(f"world parameter '{f.name}' has shape {value.shape}; expected {shape}") from None
            if f.name in ("terrain", "props"):
                n = nterrain if f.name == "terrain" else nprops
                ok = (np.mod(value, 1) == 0) & (value >= 0) & (value <= n - 1)
                allowed = f"{f.name} indices 0 to {n - 1}"
            elif f.name == "lift":
                ok = (value == 0) | (value == 1)
                allowed = "true or false"
            elif f.name == "delay":
                ok = np.isfinite(value) & (value >= 0) & (value <= max_delay + 1e-9)
                allowed = f"[0, {max_delay:g}] s (SimConfig.max_delay)"
            else:
                lo, hi = FACTOR_BOUNDS[f.name]
                ok = np.isfinite(value) & (value >= lo) & (value <= hi)
                allowed = f"[{lo:g}, {hi:g}]"
            if not ok.all():
                raise ConfigError(f"world parameter '{f.name}' has {value[~ok].flat[0]}; allowed: {allowed}")
            out[f.name] = value.astype({"terrain": int, "props": int, "lift": bool}.get(f.name, float))
        return WorldParams(**out)


def sample_uniform(rng: np.random.Generator, k: int, nbody: int, nu: int,
                   ranges: dict[str, tuple[float, float]]) -> WorldParams:
    """k worlds with each named field drawn uniformly from its (low, high) range, independently per
    world and, for per-body and per-joint fields, per body and joint; other fields nominal.

    `delay` is in seconds. The terrain is a choice, not a range: set `terrain` on the result.
    """
    p = WorldParams.nominal(k, nbody, nu)
    for name, (lo, hi) in ranges.items():
        if name not in FACTOR_BOUNDS and name != "delay":
            raise ConfigError(f"cannot sample '{name}'; ranges exist for {', '.join([*FACTOR_BOUNDS, 'delay'])}")
        setattr(p, name, rng.uniform(lo, hi, np.shape(getattr(p, name))))
    return p


class NominalModel:
    """The nominal values of every randomized MjModel field, and their application to a copy."""

    def __init__(self, model: mujoco.MjModel):
        gain, bias = model.actuator_gainprm, model.actuator_biasprm
        servo = (model.actuator_gaintype == mujoco.mjtGain.mjGAIN_FIXED) & (
            model.actuator_biastype == mujoco.mjtBias.mjBIAS_AFFINE
        )
        if not (np.all(servo) and np.allclose(gain[:, 0], -bias[:, 1]) and np.all(bias[:, 2] <= 0)):
            raise ModelError("sim needs every actuator to be a position servo (u = kp (ctrl - q) - kd qd)")
        if not np.all(model.actuator_forcelimited):
            raise ModelError("sim needs every actuator to have a torque limit (forcelimited)")
        self.body_mass = model.body_mass.copy()
        self.body_inertia = model.body_inertia.copy()
        self.geom_friction = model.geom_friction.copy()
        self.gravity = model.opt.gravity.copy()
        self.kp = gain[:, 0].copy()
        self.kd = -bias[:, 2].copy()
        self.forcerange = model.actuator_forcerange.copy()
        self._scratch = mujoco.MjData(model)

    def apply(self, model: mujoco.MjModel, p: WorldParams, row: int, then=None) -> None:
        """Set world `row` of `p` on `model`, from the nominal values; `then(model)`, if given, changes
        more (e.g. the props' masses) before the derived constants are refreshed."""
        mass = p.mass_scale[row].copy()
        mass[0] = 1.0
        model.body_mass[:] = self.body_mass * mass
        model.body_inertia[:] = self.body_inertia * mass[:, None]
        model.geom_friction[:] = self.geom_friction * p.friction_scale[row]
        model.opt.gravity[:] = self.gravity * p.gravity_scale[row]
        strength = p.motor_strength[row]
        kp = self.kp * p.kp_factor[row] * strength
        kd = self.kd * p.kd_factor[row] * strength
        model.actuator_gainprm[:, 0] = kp
        model.actuator_biasprm[:, 1] = -kp
        model.actuator_biasprm[:, 2] = -kd
        model.actuator_forcerange[:] = self.forcerange * strength[:, None]
        if then is not None:
            then(model)
        mujoco.mj_setConst(model, self._scratch)

    def gains(self, p: WorldParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Effective Kp, Kd and torque limit (k, nu) of the worlds in `p`."""
        strength = p.motor_strength
        return self.kp * p.kp_factor * strength, self.kd * p.kd_factor * strength, self.forcerange[:, 1] * strength
