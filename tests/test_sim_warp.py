"""The MuJoCo Warp backend, on Warp's CPU device, steps Digit like the C backend: same model, same state,
same PD targets, worlds on the floor (one with randomized parameters and an action delay), on rough
ground and on a stair. The tracking environment on either backend gives the same observations and
rewards, and PPO learns on it as on the C backend.

MuJoCo Warp computes in float32, the C backend in float64: on the floor the tolerances are 50 to
100 times the differences measured over this horizon (docs/sim.md, "MuJoCo Warp backend"). The
first run on a machine compiles MuJoCo Warp's kernels (about 2.5 min on 2 cores, cached after that).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("warp", reason="MuJoCo Warp backend not installed (pip install 'opt2skill[gpu]')")
pytest.importorskip("mujoco_warp", reason="MuJoCo Warp backend not installed (pip install 'opt2skill[gpu]')")

from envs_support import ROBOT, exact_config, recorded_reference  # noqa: E402

from opt2skill.envs import ReferenceBank, TrackingEnv  # noqa: E402
from opt2skill.errors import ConfigError  # noqa: E402
from opt2skill.model.standing import feedforward_ctrl  # noqa: E402
from opt2skill.model.statics import gravity_compensation  # noqa: E402
from opt2skill.sim import MujocoBatchedSim, SimConfig, Stairs, TerrainGrid, WorldParams, flat, rough  # noqa: E402
from opt2skill.sim import sample_uniform  # noqa: E402
from opt2skill.sim.devices import check_device, make_sim  # noqa: E402
from opt2skill.sim.warp_sim import WarpBatchedSim  # noqa: E402

pytestmark = pytest.mark.slow  # the first run compiles MuJoCo Warp's kernels

NWORLD, NSTEP = 5, 20  # 20 policy steps = 100 physics steps of 1 ms
FLAT, UNEVEN = np.array([0, 1]), np.array([2, 3, 4])  # worlds on the floor; on rough ground or a stair
RANDOMIZED = np.array([1, 3])
CONFIG = SimConfig(nsubstep=5, nthread=1)
TABLE_II = {"mass_scale": (0.9, 1.1), "friction_scale": (0.3, 1.0), "gravity_scale": (0.9, 1.1),
            "kp_factor": (0.9, 1.1), "kd_factor": (0.9, 1.1), "motor_strength": (0.95, 1.05)}
# Largest difference allowed between the backends, per output; measured differences in docs/sim.md.
TOLERANCE = {"qpos": 5e-5, "qvel": 5e-3, "ee_pos": 5e-5, "imu_acc": 2e-2, "torque": 5e-2, "torque_mean": 5e-2,
             "contact_wrench_mean": 1.0, "point_force_mean": 1.0, "joint_acc": 1.0}


GRID = TerrainGrid(x_range=(-2.0, 2.0), y_range=(-2.0, 2.0))
TERRAINS = [flat(), rough(GRID, 0.03, seed=3), rough(GRID, 0.03, seed=4),
            Stairs(0.1, step_length=0.6, start=-0.3, n_steps=2)]  # standing on the first step


def world_params(sim) -> WorldParams:
    """Worlds 0 and 1 on the floor, 2 and 3 on two different rough grounds (lifted onto them); 1 and 3
    with every Table II parameter randomized and a 4 ms action delay."""
    p = WorldParams.nominal(NWORLD, sim.nbody, sim.nu)
    p.assign(RANDOMIZED, sample_uniform(np.random.default_rng(1), 2, sim.nbody, sim.nu, TABLE_II))
    p.delay[RANDOMIZED] = 4 * sim.physics_dt
    p.terrain[:] = [0, 0, 1, 2, 3]
    return p


@pytest.fixture(scope="module")
def both():
    """The same start, parameters and targets on both backends: their outputs, step by step."""
    rng = np.random.default_rng(0)
    stand = feedforward_ctrl(ROBOT, ROBOT.stand_qpos, gravity_compensation(ROBOT, ROBOT.stand_qpos).torque)
    qpos = np.tile(ROBOT.stand_qpos, (NWORLD, 1))
    qpos[:, 7:] += rng.normal(0, 0.02, (NWORLD, ROBOT.nu))
    qvel = rng.normal(0, 0.1, (NWORLD, ROBOT.nv))
    targets = stand + rng.normal(0, 0.1, (NSTEP, NWORLD, ROBOT.nu))
    outs = {}
    for name, sim in (("c", MujocoBatchedSim(ROBOT, NWORLD, CONFIG, terrains=TERRAINS)),
                      ("warp", WarpBatchedSim(ROBOT, NWORLD, CONFIG, terrains=TERRAINS, device="cpu"))):
        with sim:
            first = sim.reset(np.arange(NWORLD), qpos, qvel, params=world_params(sim))
            outs[name] = [first] + [sim.step(t) for t in targets]
            outs[name + "_gains"] = sim.gains()
            outs[name + "_z"] = sim.z_offset
            outs[name + "_ground"] = sim.terrain_height(first.qpos[:, None, :2])
            if name == "warp":
                views = sim.device_arrays()
                outs["views"] = {k: (v.data_ptr(), v.clone()) for k, v in views.items()}
                outs["pointers"] = {"qpos": sim.d.qpos.ptr, "qvel": sim.d.qvel.ptr, "sensordata": sim._sensors.ptr}
    return outs


@pytest.mark.parametrize("field", sorted(TOLERANCE))
def test_warp_steps_like_c_mujoco_on_the_floor_with_randomized_parameters(both, field):
    c, w = both["c"], both["warp"]
    touching = np.array([o.contact_found[FLAT] > 0 for o in c[1:]])  # (steps, worlds, feet)
    assert touching.mean() > 0.8 and not touching.all(), "feet on the floor, making and breaking contacts"
    diff = max(np.abs(getattr(a, field)[FLAT] - getattr(b, field)[FLAT]).max() for a, b in zip(c, w))
    assert diff <= TOLERANCE[field], f"{field}: backends differ by {diff:.3g}"


def test_contact_counts_gains_and_stability_agree(both):
    c, w = both["c"], both["warp"]
    for a, b in zip(c, w):
        np.testing.assert_array_equal(a.contact_found[FLAT], b.contact_found[FLAT])
        np.testing.assert_array_equal(a.point_found, b.point_found)  # hands and elbows: in the air here
        assert not a.unstable.any() and not b.unstable.any()
    for a, b in zip(both["c_gains"], both["warp_gains"]):
        np.testing.assert_array_equal(a, b)
    # the randomized world really differs from the nominal one (it moved elsewhere on both backends)
    assert np.abs(c[-1].qpos[1] - c[-1].qpos[0]).max() > 100 * TOLERANCE["qpos"]


def test_device_arrays_share_warps_memory(both):
    """The state as torch tensors without copies: same memory as Warp's arrays, the END state."""
    views, end = both["views"], both["warp"][-1]
    for name, pointer in both["pointers"].items():
        assert views[name][0] == pointer
    np.testing.assert_array_equal(views["qpos"][1].numpy(), end.qpos.astype(np.float32))
    np.testing.assert_array_equal(views["qvel"][1].numpy(), end.qvel.astype(np.float32))


def test_worlds_on_rough_ground_and_stairs_stand_on_their_own_ground(both):
    """Lifted alike onto their own heightfield or step, they land and stand on it on both backends.
    MuJoCo Warp's box-heightfield and box-box collisions make other contact sets than C MuJoCo's
    (e.g. 2 points under a foot instead of 3), so after a touchdown the states part: measured up to
    3.5 cm in 100 ms (docs/sim.md)."""
    c, w = both["c"], both["warp"]
    assert both["c_z"][FLAT].max() == 0 and both["c_z"][UNEVEN].min() > 0.005
    np.testing.assert_allclose(both["warp_z"], both["c_z"], rtol=0, atol=1e-6)  # float32 sole corners
    np.testing.assert_array_equal(both["warp_ground"], both["c_ground"])
    for out in (c, w):
        assert all((o.contact_found[UNEVEN].sum(axis=1) > 0).all() for o in out[-5:])  # on the ground ...
        assert all(o.qpos[UNEVEN, 2].min() > 0.9 for o in out)  # ... not through it
    assert max(np.abs(a.qpos[UNEVEN] - b.qpos[UNEVEN]).max() for a, b in zip(c, w)) < 0.1
    rough = UNEVEN[:2]  # they fall for a few steps before touching down, and agree until then
    assert max(np.abs(a.qpos[rough] - b.qpos[rough]).max() for a, b in zip(c[:4], w[:4])) < 1e-3


def test_tracking_env_reads_the_same_observations_and_rewards_on_both_backends():
    traj, targets = recorded_reference(steps=12)
    config = exact_config()
    results = {}
    for name in ("c", "warp"):
        bank = ReferenceBank.from_trajectories(ROBOT, [traj], config.observations.end_effectors)
        sim = (MujocoBatchedSim(ROBOT, 1, CONFIG) if name == "c" else WarpBatchedSim(ROBOT, 1, CONFIG, device="cpu"))
        with TrackingEnv(ROBOT, bank, config, 1, seed=0, sim=sim) as env:
            env.reset_worlds(np.array([0]), np.array([0]), np.array([0]))
            rows = [env.observations()]
            for t in targets[:10]:
                r = env.step(env.actions_for_targets(t[None]))
                rows.append((r.actor, r.critic, r.reward, np.array([v[0] for v in r.terms.values()])))
        results[name] = rows
    for (a_actor, a_critic, *a_rest), (b_actor, b_critic, *b_rest) in zip(results["c"], results["warp"]):
        np.testing.assert_allclose(a_actor, b_actor, rtol=0, atol=2e-3)
        np.testing.assert_allclose(a_critic, b_critic, rtol=0, atol=0.1)
        for x, y in zip(a_rest, b_rest):
            np.testing.assert_allclose(x, y, rtol=0, atol=2e-3)


def test_device_names_are_checked_with_one_clear_error():
    with pytest.raises(ConfigError, match="--device must be"):
        check_device("tpu")
    import warp

    if warp.get_cuda_device_count() == 0:
        with pytest.raises(ConfigError, match="needs an NVIDIA GPU"):
            make_sim(ROBOT, 2, CONFIG, device="cuda")
        from opt2skill.rl.session import TrainRequest

        with pytest.raises(ConfigError, match="needs an NVIDIA GPU"):  # train --device cuda: before anything is read
            TrainRequest(dataset=Path("missing"), out=Path("run"), device="cuda").check()
        assert not Path("run").exists()


def test_ppo_learns_on_the_warp_backend_as_on_the_c_backend():
    """A short PPO run (4 worlds, 12 iterations of 10 steps, rsl_rl updates) on a TrackingEnv whose
    physics is MuJoCo Warp (device "warp-cpu"): the critic's loss falls, and the run's losses are
    those of the same run on C MuJoCo (measured: equal to 6 digits over these iterations; float32
    against float64 physics may part them later, so only the first half is compared)."""
    import torch

    from opt2skill.rl.config import PPOConfig
    from opt2skill.rl.trainer import Trainer

    traj, _ = recorded_reference(steps=40)
    config = exact_config()
    bank = ReferenceBank.from_trajectories(ROBOT, [traj], config.observations.end_effectors)
    losses = {}
    for device in ("warp-cpu", "cpu"):
        torch.manual_seed(0)
        with TrackingEnv(ROBOT, bank, config, 4, seed=0, device=device) as env:
            assert isinstance(env.sim, WarpBatchedSim) == (device == "warp-cpu")
            trainer = Trainer(env, PPOConfig(rollout_seconds=0.05), seed=0)
            assert str(trainer.venv.device) == "cpu"  # Warp's CPU device: the learner on the CPU too
            trainer.warm_up_normalizers()
            figures = [trainer.train_iteration() for _ in range(12)]
            assert trainer.env_steps == 12 * trainer.batch
            losses[device] = np.array([[f["loss/value"], f["loss/surrogate"]] for f in figures])
    value = losses["warp-cpu"][:, 0]
    assert np.all(np.isfinite(losses["warp-cpu"]))
    assert value[-4:].mean() < 0.5 * value[:4].mean(), value  # measured: 10 times lower
    np.testing.assert_allclose(losses["warp-cpu"][:6], losses["cpu"][:6], rtol=0.05, atol=1e-5)


def test_the_installed_gpu_extra_equals_its_pins_and_matches_mujoco():
    import importlib.metadata as md
    import tomllib

    pyproject = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    pins = dict(dep.split("==") for dep in pyproject["project"]["optional-dependencies"]["gpu"])
    assert set(pins) == {"mujoco-warp", "warp-lang"}
    for package, version in pins.items():
        assert md.version(package) == version, (package, md.version(package), version)
    assert md.version("mujoco-warp") == md.version("mujoco")  # MuJoCo Warp releases track MuJoCo's
