"""Every per-world parameter reaches the physics, from nominal values, and only in its own world."""

import mujoco
import numpy as np
import pytest

from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.model.standing import feedforward_ctrl
from opt2skill.model.statics import gravity_compensation
from opt2skill.sim import MujocoBatchedSim, SimConfig, WorldParams
from opt2skill.sim.delay import ActionDelay

G = 9.81


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


@pytest.fixture(scope="module")
def stand_targets(robot):
    return feedforward_ctrl(robot, robot.stand_qpos, gravity_compensation(robot, robot.stand_qpos).torque)


def make_sim(robot, n, nsubstep=5):
    return MujocoBatchedSim(robot, n, SimConfig(nsubstep=nsubstep, nthread=1))


def nominal(sim):
    return WorldParams.nominal(sim.nworld, sim.nbody, sim.nu)


def stand(robot, n, lift=0.0):
    qpos = np.tile(robot.stand_qpos, (n, 1))
    qpos[:, 2] += lift
    return qpos, np.zeros((n, robot.nv))


def test_kp_and_motor_strength_scale_the_applied_torque_and_the_response(robot):
    """One physics step from rest, targets 0.01 rad off: torque = s Kp_factor Kp 0.01, and the
    joints accelerate faster with the stronger servo (robot in the air; the joints' dry friction
    makes the acceleration affine, not proportional, in the torque)."""
    sim = make_sim(robot, 3, nsubstep=1)
    p = nominal(sim)
    p.kp_factor = np.array([[1.0], [1.2], [1.0]])
    p.motor_strength = np.array([[1.0], [1.0], [0.8]])
    qpos, qvel = stand(robot, 3, lift=1.0)
    sim.reset([0, 1, 2], qpos, qvel, params=p)
    out = sim.step(qpos[:, 7:] + 0.01)
    kp = robot.config.kp
    assert np.allclose(out.torque, kp * 0.01 * np.array([[1.0], [1.2], [0.8]]), rtol=1e-12)
    acc = np.abs(out.joint_acc[:, :12])  # legs
    assert np.all(acc[1] > 1.1 * acc[0]) and np.all(acc[2] < 0.9 * acc[0])


def test_kd_scales_the_damping_torque(robot):
    sim = make_sim(robot, 2, nsubstep=1)
    p = nominal(sim)
    p.kd_factor = np.array([[1.0], [0.9]])
    qpos, qvel = stand(robot, 2, lift=1.0)
    qvel[:, 6:] = 0.5
    sim.reset([0, 1], qpos, qvel, params=p)
    out = sim.step(qpos[:, 7:])
    assert np.allclose(out.torque, -0.5 * robot.config.kd * np.array([[1.0], [0.9]]), rtol=1e-12)


def test_motor_strength_scales_the_torque_limit(robot):
    sim = make_sim(robot, 2, nsubstep=1)
    p = nominal(sim)
    p.motor_strength = np.array([[1.0], [1.05]])
    qpos, qvel = stand(robot, 2, lift=1.0)
    sim.reset([0, 1], qpos, qvel, params=p)
    out = sim.step(qpos[:, 7:] + 3.0)  # far beyond what the limits allow
    assert np.allclose(out.torque, robot.config.torque_limit * np.array([[1.0], [1.05]]), rtol=1e-12)
    assert np.allclose(sim.gains()[2], out.torque)


def test_gravity_scale_sets_the_free_fall_acceleration(robot):
    sim = make_sim(robot, 2)
    p = nominal(sim)
    p.gravity_scale = np.array([1.0, 0.9])
    qpos, qvel = stand(robot, 2, lift=1.0)
    sim.reset([0, 1], qpos, qvel, params=p)
    out = sim.step(qpos[:, 7:])
    assert np.allclose(out.qvel[:, 2] / sim.policy_dt, [-G, -0.9 * G], rtol=1e-9)


def test_mass_scale_changes_the_weight_on_the_feet(robot, stand_targets):
    """Standing still, the feet carry the robot's weight: sum m_i s_i g, with each link scaled."""
    sim = make_sim(robot, 3)
    p = nominal(sim)
    p.mass_scale[1] = 1.1
    p.mass_scale[2] = np.random.default_rng(0).uniform(0.9, 1.1, p.mass_scale.shape[1])
    sim.reset([0, 1, 2], *stand(robot, 3), params=p)
    masses = np.array([m.body_mass.sum() for m in sim.models])
    for _ in range(200):
        sim.step(np.tile(stand_targets, (3, 1)))
    loads = [sim.step(np.tile(stand_targets, (3, 1))).contact_wrench_mean[:, :, 2].sum(1) for _ in range(40)]
    weight = np.mean(loads, axis=0)
    nominal_mass = robot.mj_model.body_mass.sum()
    expected = np.array([1.0, 1.1, 1.0]) * nominal_mass
    expected[2] = (robot.mj_model.body_mass * p.mass_scale[2]).sum()
    assert np.allclose(masses, expected, rtol=1e-12)
    assert np.allclose(weight / G, expected, rtol=5e-3)


def test_friction_scale_bounds_the_tangential_force(robot, stand_targets):
    """The robot moving at 1 m/s on its feet: with friction 0.3 the feet slide and the contact force
    sits on the cone |Ft| = 0.3 Fn; with 1.0 it goes well past 0.3 and the feet slide less."""
    sim = make_sim(robot, 2)
    p = nominal(sim)
    p.friction_scale = np.array([0.3, 1.0])
    qpos, qvel = stand(robot, 2)
    qvel[:, 0] = 1.0
    sim.reset([0, 1], qpos, qvel, params=p)
    ratio = np.zeros(2)
    for _ in range(30):
        out = sim.step(np.tile(stand_targets, (2, 1)))
        w = out.contact_wrench
        loaded = w[..., 2] > 50.0
        r = np.where(loaded, np.linalg.norm(w[..., :2], axis=-1) / np.maximum(w[..., 2], 1.0), 0.0)
        ratio = np.maximum(ratio, r.max(1))
    assert 0.299 < ratio[0] <= 0.3 + 1e-6
    assert ratio[1] > 0.45
    slide = out.ee_pos[:, list(robot.config.end_effectors).index("left_foot"), 0]
    assert slide[0] > slide[1] + 0.005


def test_parameters_are_applied_from_nominal_values_and_never_compound(robot):
    sim = make_sim(robot, 2)
    p = nominal(sim)
    p.mass_scale[:] = 1.1
    p.friction_scale[:] = 0.5
    p.kp_factor[:] = 1.1
    for _ in range(3):
        sim.set_params([0], p.rows(np.array([0])))
    m, ref = sim.models[0], robot.mj_model
    assert np.allclose(m.body_mass, ref.body_mass * np.r_[1.0, np.full(m.nbody - 1, 1.1)])
    assert np.allclose(m.geom_friction, ref.geom_friction * 0.5)
    assert np.allclose(m.actuator_gainprm[:, 0], robot.config.kp * 1.1)
    assert np.array_equal(sim.models[1].body_mass, ref.body_mass)  # the other world is untouched
    sim.set_params([0], nominal(sim).rows(np.array([0])))
    for field in ("body_mass", "body_inertia", "geom_friction", "actuator_gainprm", "actuator_biasprm",
                  "actuator_forcerange", "body_invweight0", "dof_invweight0"):
        assert np.allclose(getattr(m, field), getattr(ref, field), rtol=1e-12), field


def test_out_of_range_parameters_are_rejected(robot):
    sim = make_sim(robot, 2)
    p = nominal(sim)
    p.friction_scale = np.array([1.0, -0.1])
    with pytest.raises(ConfigError, match="friction_scale"):
        sim.set_params([0, 1], p)
    p = nominal(sim)
    p.kp_factor = np.ones((2, 3))
    with pytest.raises(ConfigError, match="kp_factor.*shape"):
        sim.set_params([0, 1], p)
    p = nominal(sim)
    p.terrain = np.array([0, 1])
    with pytest.raises(ConfigError, match="terrain"):
        sim.set_params([0, 1], p)


@pytest.mark.parametrize("delay", [0, 3, 7, 12])
def test_delay_shifts_the_response_by_whole_physics_steps(robot, delay):
    """A step in the targets at policy step 2 changes the applied torque exactly `delay` physics
    steps later (one physics step per policy step here, so each step's torque is visible)."""
    sim = make_sim(robot, 2, nsubstep=1)
    p = nominal(sim)
    p.delay = np.array([0.0, delay * sim.physics_dt])
    qpos, qvel = stand(robot, 2, lift=1.0)
    sim.reset([0, 1], qpos, qvel, params=p)
    targets = qpos[:, 7:].copy()
    torques = []
    for t in range(20):
        torques.append(sim.step(targets + (0.2 if t >= 2 else 0.0)).torque[:, 3])
    torques = np.array(torques)
    first = np.argmax(np.abs(torques) > 50.0, axis=0)
    assert first.tolist() == [2, 2 + delay]
    # In free fall both worlds then move alike, so the delayed one repeats the other's torques, shifted.
    assert np.allclose(torques[2 + delay:, 1], torques[2:20 - delay, 0], rtol=1e-9, atol=1e-9)


def test_delay_schedule_across_substeps():
    """With 5 substeps, a delay of 7 physics steps applies the targets of 2 policy steps ago for
    substeps 0-1 and of 1 policy step ago for substeps 2-4; the first targets fill the past."""
    delay = ActionDelay(nworld=2, nu=1, nsubstep=5, max_delay=20)
    delay.set_delay(np.array([0, 1]), np.array([0, 7]))
    seqs = [delay.sequence(np.array([[t], [t]], dtype=float))[:, :, 0] for t in range(1, 5)]
    assert seqs[0].tolist() == [[1] * 5, [1] * 5]
    assert seqs[2].tolist() == [[3] * 5, [1, 1, 2, 2, 2]]
    assert seqs[3].tolist() == [[4] * 5, [2, 2, 3, 3, 3]]
    delay.clear(np.array([1]), targets=np.array([[9.0]]))
    assert delay.sequence(np.array([[5.0], [5.0]]))[1, :, 0].tolist() == [9, 9, 9, 9, 9]
