"""The optimizer's feedback law drives MuJoCo along a real walk; its conversions are exact; its standing
gains (an infinite-horizon LQR) hold the robot where DDP's horizon ends; it acts in the tracking
environment through the policy's action space."""

from dataclasses import replace

import numpy as np
import pinocchio as pin
import pytest

from opt2skill.data.record import FRAME_DT
from opt2skill.envs import ReferenceBank, TrackingEnv, evaluation_config, tracking_config
from opt2skill.envs.evaluation import track
from opt2skill.envs.measure import Readings
from opt2skill.errors import ConfigError, DataError
from opt2skill.eval.metrics import tracking_errors
from opt2skill.expert import FeedbackExpert, pd_targets, servo_torque
from opt2skill.expert.acting import EnvExpert, ExpertConfig
from opt2skill.expert.lie import state_diff
from opt2skill.expert.standing import StandingLQR, standing_segments
from opt2skill.model import load_robot
from opt2skill.sim import MujocoBatchedSim, SimConfig
from opt2skill.tasks import get_task


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


@pytest.fixture(scope="module")
def walk(robot):
    """A real 3-s, 4-step walk at 0.5 m/s with the solver's feedback gains."""
    task = get_task("walk", robot, {"solver.keep_gains": True, "steps": 4, "duration": 3.0})
    space = task.param_space()
    params = space.check({**space.sample(0, 0), "speed": 0.5, "clearance": 0.12, "step_duration": 0.35,
                          "double_support": 0.2, "height_offset": -0.02})
    return task.solve(params, seed=0)


def test_state_difference_equals_pinocchio(robot):
    pm, rng = robot.pin_model, np.random.default_rng(0)
    lo, hi = pm.lowerPositionLimit.copy(), pm.upperPositionLimit.copy()
    lo[:3], hi[:3] = -2.0, 2.0
    x0, x1, expected = [], [], []
    for i in range(60):
        q0 = pin.randomConfiguration(pm, lo, hi)
        # Far apart, nearby, and nearly equal configurations (the small-angle series).
        q1 = pin.randomConfiguration(pm, lo, hi) if i % 3 == 0 else pin.integrate(pm, q0, rng.normal(scale=(0.3, 1e-7)[i % 3 - 1], size=pm.nv))
        v0, v1 = rng.normal(size=pm.nv), rng.normal(size=pm.nv)
        x0.append(np.r_[q0, v0]), x1.append(np.r_[q1, v1])
        expected.append(np.r_[pin.difference(pm, q0, q1), v1 - v0])
    assert np.abs(state_diff(np.array(x0), np.array(x1), pm.nq) - np.array(expected)).max() < 1e-10


def test_torque_to_target_to_torque_round_trip_is_exact(robot):
    rng = np.random.default_rng(1)
    kp = robot.config.kp * rng.uniform(0.9, 1.1, (8, robot.nu))
    kd = robot.config.kd * rng.uniform(0.9, 1.1, (8, robot.nu))
    torque = rng.uniform(-1, 1, (8, robot.nu)) * robot.config.torque_limit
    q, qd = rng.normal(size=(8, robot.nu)), rng.normal(scale=3, size=(8, robot.nu))
    assert np.allclose(servo_torque(pd_targets(torque, q, qd, kp, kd), q, qd, kp, kd), torque, rtol=0, atol=1e-10)


def run(robot, walk, sign: float, nsubstep: int, perturb: bool):
    """Track the walk with u = u_ref - sign * K dx; returns (alive, mean foot error m, mean joint error rad)."""
    scaled = replace(walk, knots={**walk.knots, "gains": sign * walk.knots["gains"]})
    expert = FeedbackExpert(robot, [scaled])
    n = 3
    sim = MujocoBatchedSim(robot, n, SimConfig(nsubstep=nsubstep))
    qpos, qvel = np.repeat(walk.qpos[:1], n, 0), np.repeat(walk.qvel[:1], n, 0)
    if perturb:  # base shifted 2 cm, joints off by 0.02 rad (std), base pushed at 0.2 m/s
        qpos[0, 0] += 0.02
        qpos[1, 7:] += np.random.default_rng(2).normal(scale=0.02, size=robot.nu)
        qvel[2, 0] += 0.2
    out = sim.reset(np.arange(n), qpos, qvel)
    kp, kd, _ = sim.gains()
    feet = [walk.ee_names.index("left_foot"), walk.ee_names.index("right_foot")]
    alive, foot_err, joint_err, t = np.ones(n, bool), [], [], 0.0
    for _ in range(int(round(walk.duration / sim.policy_dt))):
        u = expert.torque(np.zeros(n, int), np.full(n, t), out.qpos, out.qvel)
        out = sim.step(pd_targets(u, out.joint_pos, out.joint_vel, kp, kd))
        t += sim.policy_dt
        f = min(int(round(t / FRAME_DT)), walk.num_frames - 1)
        alive &= out.qpos[:, 2] > 0.7
        foot_err.append(np.linalg.norm(out.ee_pos[:, feet] - walk.ee_pos[f, feet], axis=-1).mean(1))
        joint_err.append(np.abs(out.joint_pos - walk.qpos[f, 7:]).mean(1))
    sim.close()
    return alive, np.mean(foot_err, axis=0), np.mean(joint_err, axis=0)


@pytest.mark.parametrize("nsubstep", [1, 5], ids=["physics_rate", "policy_rate"])
def test_perturbed_starts_converge_under_the_expert_in_mujoco(robot, walk, nsubstep):
    alive, foot, joint = run(robot, walk, sign=1.0, nsubstep=nsubstep, perturb=True)
    assert alive.all()
    assert foot.max() < 0.03 and joint.max() < 0.03  # measured about 1 cm and 0.01 rad


def test_without_feedback_or_with_the_wrong_sign_the_walk_is_lost(robot, walk):
    """The sign convention matters: flipping it (or dropping the feedback) makes tracking much worse."""
    _, good_foot, _ = run(robot, walk, sign=1.0, nsubstep=5, perturb=False)
    for sign in (0.0, -1.0):
        alive, foot, _ = run(robot, walk, sign=sign, nsubstep=5, perturb=False)
        assert (not alive.all()) or foot.mean() > 3 * good_foot.mean()


def test_trajectories_without_gains_get_a_clear_error(robot, walk):
    bare = replace(walk, knots={k: v for k, v in walk.knots.items() if k != "gains"})
    with pytest.raises(DataError, match="no feedback gains.*--keep-gains"):
        FeedbackExpert(robot, [walk, bare])


def test_standing_segments_are_the_walks_start_and_end(robot, walk):
    feet = [f.name for f in robot.config.feet]
    segments = standing_segments(walk, StandingLQR(), feet)
    assert len(segments) == 2
    (a0, b0), (a1, b1) = segments
    assert a0 == 0 and b1 == walk.num_frames
    assert walk.contact_active[a0:b0].all() and walk.contact_active[a1:b1].all()
    # Walking double supports are far shorter than a standing segment.
    assert not walk.contact_active[b0:a1].all(axis=1)[: int(0.5 / FRAME_DT)].all()
    # A record with a contact the standing LQR does not know (a hand) keeps the solver's gains.
    assert standing_segments(walk, StandingLQR(), feet[:1]) == []


def test_standing_gains_are_solved_once_per_process_and_again_for_another_state(robot, walk):
    from opt2skill.expert.standing import GAIN_CACHE

    first = FeedbackExpert(robot, [walk])
    solved = GAIN_CACHE.solved
    second = FeedbackExpert(robot, [walk])  # the same references again (a PPO stage's anchor): no solve
    assert GAIN_CACHE.solved == solved
    assert np.array_equal(first._gains, second._gains)
    # Another torque at a segment's middle frame is another linearization: solved, and a different gain.
    (a, b), _ = standing_segments(walk, StandingLQR(), [f.name for f in robot.config.feet])
    torque = walk.joint_torque.copy()
    torque[(a + b) // 2] *= 1.2
    third = FeedbackExpert(robot, [replace(walk, joint_torque=torque)])
    assert GAIN_CACHE.solved == solved + 1
    assert not np.array_equal(third._gains, first._gains)


def hold_after_end(robot, walk, standing, push: float) -> np.ndarray:
    """Run the expert from 0.5 s before the walk's end to 2.5 s after it, pushing the base forward
    by `push` m/s at the end; the final base deviation from the last frame (m)."""
    expert = FeedbackExpert(robot, [walk], standing)
    sim = MujocoBatchedSim(robot, 1, SimConfig(nsubstep=5, nthread=1))
    frame = walk.num_frames - 1 - int(0.5 / FRAME_DT)
    out = sim.reset(np.arange(1), walk.qpos[frame:frame + 1], walk.qvel[frame:frame + 1])
    kp, kd, _ = sim.gains()
    t = frame * FRAME_DT
    for k in range(int(3.0 / sim.policy_dt)):
        if k == int(0.5 / sim.policy_dt):
            qvel = out.qvel.copy()
            qvel[:, 0] += push
            out = sim.reset(np.arange(1), out.qpos, qvel, targets=out.joint_pos)
        u, dx = expert.torque_and_deviation(np.zeros(1, int), np.full(1, t), out.qpos, out.qvel)
        out = sim.step(pd_targets(u, out.joint_pos + 0.75 * sim.policy_dt * out.joint_vel, out.joint_vel, kp, kd))
        t += sim.policy_dt
    sim.close()
    return np.linalg.norm(dx[:, :3], axis=1)[0]


def test_standing_gains_hold_a_pushed_robot_after_the_reference_ends(robot, walk):
    # Measured: within 5 mm of the last frame, with and without a 0.3 m/s push.
    assert hold_after_end(robot, walk, StandingLQR(), push=0.0) < 0.01
    assert hold_after_end(robot, walk, StandingLQR(), push=0.3) < 0.02
    # DDP's own gains at its horizon's end drift 10 cm unpushed and lose the robot when pushed (1.2 m).
    assert hold_after_end(robot, walk, None, push=0.3) > 0.2


def test_the_expert_tracks_in_the_environments_action_space(robot, walk):
    config = evaluation_config(tracking_config("walk"))
    bank = ReferenceBank.from_trajectories(robot, [walk], config.observations.end_effectors)
    with TrackingEnv(robot, bank, config, 1, seed=0, threads=1) as env:
        env.set_progress(1.0)
        expert = EnvExpert(env, [walk])
        _, valid = expert.act()
        assert valid.all()  # at the reference state
        motion = track(env, expert, np.arange(1))[0]
        # A world far from its reference is outside the expert's region.
        env.reset_worlds(np.arange(1), np.zeros(1, int), np.zeros(1, int))
        qpos = env.state.qpos.copy()
        qpos[:, 0] += 0.3
        env.state.assign(np.arange(1), env.sim.reset(np.arange(1), qpos, env.state.qvel))
        assert not expert.act()[1].any()
    assert not motion.fell and motion.steps + 1 == walk.num_frames
    errors = tracking_errors(walk, motion.record(robot, walk))
    assert errors.E_joint < 0.01 and errors.E_ee_foot < 1.0  # measured 0.0011 rad, 0.14 cm


def test_the_servos_pd_around_the_reference_tracks_closer_than_the_law_alone(robot, walk):
    """The default servo form adds the servo's own PD on the reference to the law (its target is the
    reference's plus u / kp); the "state" form leaves the law alone at 200 Hz. Both walk; the PD's
    joint error is smaller (measured 0.0011 against 0.0028 rad; on heavy boxes it is
    the difference between carrying the box and dropping it, docs/distill.md)."""
    config = evaluation_config(tracking_config("walk"))
    bank = ReferenceBank.from_trajectories(robot, [walk], config.observations.end_effectors)
    joint_error = {}
    for servo in ("reference", "state"):
        with TrackingEnv(robot, bank, config, 1, seed=0, threads=1) as env:
            env.set_progress(1.0)
            expert = EnvExpert(env, [walk], ExpertConfig(servo=servo))
            if servo == "reference":
                # the target at the reference: the reference's joints plus (u + kd qd_ref) / kp
                q_ref, qd_ref = expert.expert.reference_joints(np.zeros(1, int), np.full(1, 0.5 * env.sim.policy_dt))
                u = expert.expert.torque(np.zeros(1, int), np.zeros(1), env.state.qpos, env.state.qvel)
                u = u + expert._damping * env.state.joint_vel
                kp, kd, _ = env.sim.gains()
                np.testing.assert_allclose(expert.act()[0], env.actions_for_targets(q_ref + (u + kd * qd_ref) / kp),
                                           atol=1e-6)
            motion = track(env, expert, np.arange(1))[0]
        assert not motion.fell
        joint_error[servo] = tracking_errors(walk, motion.record(robot, walk)).E_joint
    assert joint_error["reference"] < 0.5 * joint_error["state"], joint_error


def test_bad_expert_settings_get_clear_errors(robot, walk):
    with pytest.raises(ConfigError, match="lead"):
        ExpertConfig(lead=-1).check()
    with pytest.raises(ConfigError, match="servo must be one of reference, state"):
        ExpertConfig(servo="torque").check()
    with pytest.raises(ConfigError, match="reference_ahead"):
        ExpertConfig(reference_ahead=9).check()
    with pytest.raises(ConfigError, match="max_joint"):
        ExpertConfig(max_joint=-0.1).check()


@pytest.mark.parametrize("servo, gain_range", [("state", (0.6, 1.0)), ("reference", (-0.4, 0.0))])
def test_reading_the_observations_the_expert_labels_what_the_actor_sees_and_still_walks(robot, walk, servo, gain_range):
    """Under Table II's noise the expert that reads the actor's own readings (a perfect student with
    noisy inputs) acts on the observation (its targets move with the read joint positions, not the true
    ones), is unchanged without noise and judges validity on the true state."""
    config = evaluation_config(tracking_config("walk"), noise=True)
    bank = ReferenceBank.from_trajectories(robot, [walk], config.observations.end_effectors)
    with TrackingEnv(robot, bank, config, 1, seed=0, threads=1) as env:
        env.set_progress(1.0)  # the noise at full strength
        reading = EnvExpert(env, [walk], ExpertConfig(reads="observations", servo=servo))
        state = EnvExpert(env, [walk], ExpertConfig(servo=servo))
        env.reset()  # the history is filled with readings at the current noise
        assert np.abs(env.readings.joint_pos - env.state.joint_pos).max() > 0.05  # Table II: 0.0875 rad
        assert np.abs(reading.act()[0] - state.act()[0]).max() > 0.05
        # Readings exact but for the joint positions: the "state" servo's target follows the read
        # position at a gain of about 1 - K_q / Kp (DDP's joint gains are a median 16 % of the
        # servo's); the "reference" servo's target sits at the reference and moves only through the
        # law's feedback, -K_q / Kp
        m = env.m
        offset = 0.01 * np.random.default_rng(0).choice([-1.0, 1.0], env.nu)
        env.readings = Readings(m.joint_pos + offset, m.joint_vel, m.base_lin_vel, m.base_ang_vel, m.gravity)
        gain = np.median((reading.act()[0] - state.act()[0]) * env.action_scale / offset)
        assert gain_range[0] < gain < gain_range[1], gain
        env.observations()
        assert reading.act()[1].all()  # valid: judged on the true state
        motion = track(env, reading, np.arange(1))[0]
        env.noise_factor = 0.0
        env.observations()
        np.testing.assert_allclose(reading.act()[0], state.act()[0], atol=1e-12)
    # measured: the "reference" servo walks all of the walk's 600 steps through Table II's full noise,
    # the "state" servo 211; held-out 14-s walks are lost within seconds at full noise by both
    # (docs/distill.md, benchmarks/expert_noise.py)
    assert motion.steps > (500 if servo == "reference" else 100), motion.steps
    with pytest.raises(ConfigError, match="reads"):
        ExpertConfig(reads="truth").check()
