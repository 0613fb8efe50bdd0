"""The batched simulator steps each world exactly as an independent MuJoCo loop would, and isolates failures."""

from dataclasses import replace

import mujoco
import numpy as np
import pytest

from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.model.sensors import SensorLayout
from opt2skill.model.standing import feedforward_ctrl
from opt2skill.model.statics import gravity_compensation
from opt2skill.sim import MujocoBatchedSim, SimConfig, WorldParams
from opt2skill.sim.params import sample_uniform

NWORLD, NSTEP, S = 6, 30, 5


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


@pytest.fixture(scope="module")
def stand_targets(robot):
    """PD targets that hold the stand pose: gravity compensation through the servo targets."""
    return feedforward_ctrl(robot, robot.stand_qpos, gravity_compensation(robot, robot.stand_qpos).torque)


TABLE_II = {"mass_scale": (0.9, 1.1), "friction_scale": (0.3, 1.0), "gravity_scale": (0.9, 1.1),
            "kp_factor": (0.9, 1.1), "kd_factor": (0.9, 1.1), "motor_strength": (0.95, 1.05)}


def random_params(sim, seed):
    p = sample_uniform(np.random.default_rng(seed), sim.nworld, sim.nbody, sim.nu, TABLE_II)
    p.delay = np.arange(sim.nworld) * 4 * sim.physics_dt  # 0, 4, 8, ... physics steps
    return p


def start_states(robot, n, seed):
    rng = np.random.default_rng(seed)
    qpos = np.tile(robot.stand_qpos, (n, 1))
    qpos[:, 7:] += rng.normal(0, 0.03, (n, robot.nu))
    qvel = rng.normal(0, 0.2, (n, robot.nv))
    return qpos, qvel


def target_sequence(stand_targets, nstep, n, seed, scale=0.15):
    rng = np.random.default_rng(seed)
    return stand_targets + rng.normal(0, scale, (nstep, n, stand_targets.size))


def run(sim, robot, targets, seed=0):
    qpos, qvel = start_states(robot, sim.nworld, seed)
    sim.reset(np.arange(sim.nworld), qpos, qvel, params=random_params(sim, seed))
    return [sim.step(t) for t in targets]


@pytest.fixture(scope="module")
def batched(robot, stand_targets):
    targets = target_sequence(stand_targets, NSTEP, NWORLD, seed=1)
    with MujocoBatchedSim(robot, NWORLD, SimConfig(nsubstep=S, nthread=2)) as sim:
        outs = run(sim, robot, targets)
        models = sim.models
        delays = np.rint(sim.params.delay / sim.physics_dt).astype(int)
    return targets, outs, models, delays


def reference_loop(robot, model, qpos, qvel, targets, delay):
    """One world in a plain MjData loop: delayed targets per physics step, zero warm start per policy step."""
    d = mujoco.MjData(model)
    d.qpos[:], d.qvel[:] = qpos, qvel
    layout_outputs = []
    for t in range(len(targets)):
        d.qacc_warmstart[:] = 0.0
        readings = []
        for j in range(S):
            n = t * S + j
            d.ctrl[:] = targets[max(0, (n - delay) // S)]
            mujoco.mj_step(model, d)
            readings.append(d.sensordata.copy())
        layout_outputs.append((d.time, d.qpos.copy(), d.qvel.copy(), np.array(readings)))
    return layout_outputs, d


def test_batched_step_equals_independent_loops(robot, batched):
    targets, outs, models, delays = batched
    qpos, qvel = start_states(robot, NWORLD, 0)
    assert len(set(delays)) > 1  # the worlds really have different delays
    layout = SensorLayout.from_model(models[0], robot.config)
    for w in range(NWORLD):
        ref, _ = reference_loop(robot, models[w], qpos[w], qvel[w], targets[:, w], delays[w])
        for t, (time, qp, qv, readings) in enumerate(ref):
            out = outs[t]
            assert out.time[w] == time
            assert np.array_equal(out.qpos[w], qp) and np.array_equal(out.qvel[w], qv)
            assert np.array_equal(out.torque[w], readings[-1][layout.joint_torque])
            assert np.allclose(out.torque_mean[w], readings[:, layout.joint_torque].mean(0), rtol=0, atol=1e-9)
            wrench = layout.contact_wrench(readings, readings[:, layout.sole_pos])
            assert np.allclose(out.contact_wrench[w], wrench[-1], rtol=0, atol=1e-9)
            assert np.allclose(out.contact_wrench_mean[w], wrench.mean(0), rtol=0, atol=1e-9)
    assert not any(o.unstable.any() for o in outs)


def test_end_of_step_outputs_describe_the_post_step_state(robot, batched):
    """IMU and joint outputs equal MuJoCo's own sensors after mj_forward at the post-step state;
    end-effector positions, carried over the last physics step, are within 0.05 mm of them."""
    targets, outs, models, delays = batched
    layout = SensorLayout.from_model(models[0], robot.config)
    worst = 0.0
    for w in range(NWORLD):
        d = mujoco.MjData(models[w])
        for out in outs[::3]:
            d.qpos[:], d.qvel[:] = out.qpos[w], out.qvel[w]
            mujoco.mj_forward(models[w], d)
            s = d.sensordata
            assert np.allclose(out.imu_quat[w], s[layout.imu_quat], atol=1e-12)
            assert np.allclose(out.imu_gyro[w], s[layout.imu_gyro], atol=1e-12)
            assert np.allclose(out.imu_linvel[w], s[layout.imu_linvel], atol=1e-12)
            assert np.array_equal(out.joint_pos[w], s[layout.joint_pos])
            assert np.array_equal(out.joint_vel[w], s[layout.joint_vel])
            worst = max(worst, float(np.abs(out.ee_pos[w] - s[layout.ee_pos]).max()))
    assert worst < 5e-5
    speeds = np.abs(np.stack([o.qvel[:, 6:] for o in outs])).max()
    assert speeds > 2.0  # the motion was lively enough for the bound to mean something


def test_joint_acceleration_is_the_mean_over_the_policy_step(batched):
    targets, outs, models, delays = batched
    dt = S * models[0].opt.timestep
    for prev, out in zip(outs[:-1], outs[1:]):
        assert np.allclose(out.joint_acc, (out.joint_vel - prev.joint_vel) / dt, atol=1e-9)


def test_deterministic_across_runs_and_thread_counts(robot, stand_targets, batched):
    targets, outs, _, _ = batched
    for config in (SimConfig(nsubstep=S, nthread=1), SimConfig(nsubstep=S, nthread=2)):
        with MujocoBatchedSim(robot, NWORLD, config) as sim:
            again = run(sim, robot, targets)
        for a, b in zip(outs, again):
            assert np.array_equal(a.qpos, b.qpos) and np.array_equal(a.qvel, b.qvel)
            assert np.array_equal(a.contact_wrench_mean, b.contact_wrench_mean)


def test_resetting_some_worlds_leaves_the_others_untouched(robot, batched):
    targets, outs, _, _ = batched
    chosen = np.array([1, 4])
    with MujocoBatchedSim(robot, NWORLD, SimConfig(nsubstep=S, nthread=2)) as sim:
        qpos, qvel = start_states(robot, NWORLD, 0)
        sim.reset(np.arange(NWORLD), qpos, qvel, params=random_params(sim, 0))
        for t in range(NSTEP):
            if t == 10:
                sim.reset(chosen, np.tile(robot.stand_qpos, (2, 1)), np.zeros((2, robot.nv)))
            out = sim.step(targets[t])
            others = np.setdiff1d(np.arange(NWORLD), chosen)
            assert np.array_equal(out.qpos[others], outs[t].qpos[others])
            if t >= 10:
                assert not np.array_equal(out.qpos[chosen], outs[t].qpos[chosen])
                assert np.allclose(out.time[chosen], (t - 9) * sim.policy_dt)


def test_reset_outputs_describe_the_reset_state(robot, stand_targets):
    with MujocoBatchedSim(robot, 2, SimConfig(nthread=1)) as sim:
        qpos, qvel = start_states(robot, 2, 3)
        out = sim.reset([0, 1], qpos, qvel, targets=np.tile(stand_targets, (2, 1)))
        assert np.array_equal(out.qpos, qpos) and np.array_equal(out.qvel, qvel)
        assert np.all(out.time == 0.0) and np.all(out.joint_acc == 0.0)
        d = mujoco.MjData(sim.models[0])
        d.qpos[:], d.qvel[:], d.ctrl[:] = qpos[0], qvel[0], stand_targets
        mujoco.mj_forward(sim.models[0], d)
        assert np.allclose(out.torque[0], d.actuator_force)
        assert np.allclose(out.ee_pos[0], d.site_xpos[[robot.site_id(s) for s in robot.config.end_effectors.values()]])
        assert out.contact_wrench_mean[0, :, 2].sum() > 200.0  # standing: the feet carry the robot


def test_diverging_world_is_flagged_held_and_isolated(robot, stand_targets):
    targets = target_sequence(stand_targets, 6, 4, seed=5, scale=0.02)
    with MujocoBatchedSim(robot, 4, SimConfig(nthread=2)) as sim:
        clean = [sim.step(t) for t in targets]
    poisoned = targets.copy()
    poisoned[3, 2, 5] = np.nan  # a diverged policy sends NaN to world 2 at step 3
    with MujocoBatchedSim(robot, 4, SimConfig(nthread=2)) as sim:
        outs = [sim.step(t) for t in poisoned]
        assert [bool(o.unstable[2]) for o in outs[:4]] == [False, False, False, True]
        for o, c in zip(outs, clean):
            assert np.array_equal(o.qpos[[0, 1, 3]], c.qpos[[0, 1, 3]])  # the others never notice
            assert all(np.all(np.isfinite(v)) for v in vars(o).values())
        assert np.array_equal(outs[3].qpos[2], outs[2].qpos[2])  # held at its state before the step
        # An exploding world (speed beyond the bound) is flagged too; after a reset it runs again.
        qvel = np.zeros((1, robot.nv))
        qvel[0, 2] = 2 * sim.config.max_speed
        sim.reset([1, 2], np.tile(robot.stand_qpos, (2, 1)), np.zeros((2, robot.nv)))
        sim.reset([1], robot.stand_qpos[None], qvel)
        out = sim.step(targets[0])
        assert out.unstable.tolist() == [False, True, False, False]
        assert np.array_equal(out.qvel[1], qvel[0])


def test_torques_stay_within_the_limits(robot, stand_targets):
    wild = target_sequence(stand_targets, 20, 3, seed=7, scale=2.0)
    with MujocoBatchedSim(robot, 3, SimConfig(nthread=1)) as sim:
        p = WorldParams.nominal(3, sim.nbody, sim.nu)
        p.motor_strength = np.array([[1.0], [0.95], [1.05]])
        sim.set_params([0, 1, 2], p)
        limit = sim.gains()[2]
        ratio = np.stack([np.abs(sim.step(t).torque) / limit for t in wild])
    assert ratio.max() <= 1.0 + 1e-12
    assert (ratio > 1.0 - 1e-9).mean() > 0.1  # often saturated, so the limit was really in play


def test_bad_input_is_a_clear_error(robot):
    with MujocoBatchedSim(robot, 2, SimConfig(nthread=1)) as sim:
        with pytest.raises(ConfigError, match="targets must have shape"):
            sim.step(np.zeros((3, robot.nu)))
        with pytest.raises(ConfigError, match="qpos contains non-finite"):
            sim.reset([0], np.full((1, robot.nq), np.nan), np.zeros((1, robot.nv)))
        with pytest.raises(ConfigError, match="world indices"):
            sim.reset([0, 0], np.zeros((2, robot.nq)), np.zeros((2, robot.nv)))
        p = WorldParams.nominal(1, sim.nbody, sim.nu)
        p.delay = np.array([0.5])
        with pytest.raises(ConfigError, match="'delay'.*allowed"):
            sim.set_params([0], p)
    with pytest.raises(ConfigError, match="nsubstep"):
        SimConfig(nsubstep=0)


def test_two_kilohertz_player_configuration(robot, stand_targets):
    """The sim-to-sim player: 10 physics steps of 0.5 ms per 5 ms policy step, delays in seconds."""
    config = SimConfig(nsubstep=10, physics_dt=0.0005, nthread=1)
    with MujocoBatchedSim(robot, 2, config) as sim:
        assert sim.physics_dt == 0.0005 and sim.policy_dt == pytest.approx(0.005)
        p = sim.params
        p.delay = np.array([0.0, 0.0125])  # 25 physics steps at 2 kHz
        sim.set_params([0, 1], p)
        for _ in range(200):
            out = sim.step(np.tile(stand_targets, (2, 1)))
        assert np.allclose(out.time, 1.0) and not out.unstable.any()
        assert np.all(out.qpos[:, 2] > 1.0)  # standing


def test_outputs_survive_later_steps(robot, stand_targets):
    """Outputs are fresh arrays: an environment may keep them (histories) while stepping on."""
    with MujocoBatchedSim(robot, 2, SimConfig(nthread=1)) as sim:
        first = sim.step(np.tile(stand_targets, (2, 1)))
        kept = {name: np.copy(value) for name, value in vars(first).items()}
        for _ in range(3):
            sim.step(np.tile(stand_targets, (2, 1)) + 0.3)
        for name, value in vars(first).items():
            assert np.array_equal(value, kept[name]), name


def test_imu_mounted_off_the_base_origin(digit_copy):
    """A robot whose IMU sits away from the base origin, rotated: the END IMU outputs still equal
    MuJoCo's own sensors at the post-step state."""
    xml = digit_copy / "digit.xml"
    xml.write_text(xml.read_text().replace(
        '<site name="imu" pos="0 0 0" size="0.01"/>',
        '<site name="imu" pos="0.05 -0.03 0.2" quat="0.9238795 0.2 0.3 0.1" size="0.01"/>'))
    robot = load_robot(digit_copy / "robot.yaml")
    targets = feedforward_ctrl(robot, robot.stand_qpos, gravity_compensation(robot, robot.stand_qpos).torque)
    with MujocoBatchedSim(robot, 2, SimConfig(nthread=1)) as sim:
        qpos, qvel = start_states(robot, 2, seed=9)
        sim.reset([0, 1], qpos, qvel)
        out = sim.step(np.tile(targets, (2, 1)))
        layout = SensorLayout.from_model(sim.models[0], robot.config)
        for w in range(2):
            d = mujoco.MjData(sim.models[w])
            d.qpos[:], d.qvel[:] = out.qpos[w], out.qvel[w]
            mujoco.mj_forward(sim.models[w], d)
            s = d.sensordata
            assert np.abs(s[layout.imu_quat] - [1, 0, 0, 0]).max() > 0.1  # really mounted rotated
            assert np.allclose(out.imu_quat[w], s[layout.imu_quat], atol=1e-12)
            assert np.allclose(out.imu_gyro[w], s[layout.imu_gyro], atol=1e-12)
            assert np.allclose(out.imu_linvel[w], s[layout.imu_linvel], atol=1e-12)


def test_sensor_groups_are_taken_as_views_or_copies_alike(robot):
    """SensorLayout.take gives the fancy-indexed values, as a view for contiguous groups."""
    layout = SensorLayout.from_model(robot.mj_model, robot.config)
    data = np.random.default_rng(0).normal(size=(3, 5, robot.mj_model.nsensordata))
    shuffled = replace(layout, joint_torque=layout.joint_torque[::-1].copy())
    for lay, group in ((layout, "contact"), (layout, "joint_torque"), (shuffled, "joint_torque")):
        taken = lay.take(data, group)
        assert np.array_equal(taken, data[..., getattr(lay, group)])
        assert np.shares_memory(taken, data) == (lay is layout)
