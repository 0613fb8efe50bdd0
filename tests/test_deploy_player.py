"""The standalone player: its own observation code builds what the training environment builds for
the same states, it imports nothing of the training code, its latency delays the targets, and its
metrics come out in eval's report."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import mujoco
import numpy as np
import pytest
from eval_support import CLI, player_matches_environment, shared_run

from opt2skill.data.reader import Dataset
from opt2skill.deploy.export import export_policy
from opt2skill.deploy.player import Player, PlayerConfig


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    run, dataset = shared_run(tmp_path_factory)
    path, _ = export_policy(run, tmp_path_factory.mktemp("player") / "policy.onnx")
    return run, dataset, path


def test_player_observations_equal_the_training_environments_for_the_same_states(exported):
    """The environment steps with the policy's actions plus noise (so the histories hold distinct
    values); at every step the player reads its sensors at the environment's state, keeps its own
    histories and builds the observation from the metadata. Layouts, frames, histories, reference
    frames and reset fills must all agree: the vectors are equal to float32 rounding."""
    run, dataset, path = exported
    worst = player_matches_environment(run, path, Dataset.open(dataset)[1])
    assert worst < 1e-6, worst


def test_the_player_imports_nothing_of_the_training_code(exported):
    code = ("import sys, opt2skill.deploy.sim_to_sim, opt2skill.deploy.player; "
            "print(sorted(m for m in sys.modules if m.startswith(('opt2skill.envs', 'opt2skill.rl', 'opt2skill.sim', "
            "'opt2skill.trajopt', 'torch', 'rsl_rl'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.strip() == "[]"


def test_latency_delays_the_targets(exported):
    run, dataset, path = exported
    reference = Dataset.open(dataset)[0]

    def first_torque(latency, physics_dt=0.0005):
        r = Player(path, PlayerConfig(physics_dt=physics_dt, latency=latency)).run(reference)
        return r.tracked.joint_torque[0]

    now, one_step, two_steps = first_torque(0.0), first_torque(0.005), first_torque(0.010)
    # With 5 or 10 ms of latency, the first policy step still holds the start pose: the same torques.
    np.testing.assert_allclose(one_step, two_steps, atol=1e-9)
    assert np.abs(now - one_step).max() > 1.0


def test_the_servos_apply_the_metadatas_pd_law(exported):
    """u = clip(kp (target - q) - kd qd, +-limit) with the metadata's gains, not the model's own."""
    _, _, path = exported
    player = Player(path)
    rng = np.random.default_rng(1)
    player.kp, player.kd = player.kp * rng.uniform(0.5, 2.0, 20), player.kd * rng.uniform(0.5, 2.0, 20)
    player._set_servos()
    m, d = player.model, player.data
    d.qpos[:] = player.robot.stand_qpos
    d.qpos[7:] += rng.normal(0, 0.1, 20)
    d.qvel[6:] = rng.normal(0, 1.0, 20)
    d.ctrl[:] = rng.normal(0, 0.3, 20)
    mujoco.mj_forward(m, d)
    law = player.kp * (d.ctrl - d.qpos[7:]) - player.kd * d.qvel[6:]
    np.testing.assert_allclose(d.actuator_force, np.clip(law, -player.limit, player.limit), rtol=1e-9, atol=1e-9)


def test_deploy_sim_reports_evals_metrics(exported, tmp_path):
    run, dataset, path = exported
    out = tmp_path / "sim2sim"
    result = subprocess.run([CLI, "deploy-sim", str(path), "--dataset", str(dataset), "--split", "training", "--n", "2",
                             "--latency", "0.005", "--noise", "0.5", "--out", str(out), "--quiet"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    import json

    report = json.loads((out / "eval.json").read_text())
    assert report["kind"] == "deploy-sim" and len(report["trajectories"]) == 2
    assert report["options"]["substeps"] == 10 and report["options"]["latency"] == 0.005
    assert set(report["summary"]) >= {"E_joint", "E_ee_foot", "E_force", "E_torque"}
    assert "NOT held out" in report["references"]["note"]
    assert "E_joint (rad)" in (out / "eval.md").read_text()


def test_the_player_plays_a_reference_in_its_scene(exported):
    """The same reference made on the top landing of stairs (0.4 m up) plays on that landing: the
    robot moves as on the floor, 0.4 m higher (on the bare floor it would drop)."""
    from opt2skill.scene import Scene, Stairs

    _, dataset, path = exported
    reference = Dataset.open(dataset)[0]
    qpos = reference.qpos.copy()
    qpos[:, 2] += 0.4
    landing = Scene(Stairs(0.1, start=20.0, n_steps=4, landing=30.0, down=True))
    on_landing = dataclasses.replace(reference, qpos=qpos, scene=landing)
    player = Player(path)
    floor, high = player.run(reference), player.run(on_landing)
    assert player.model.nq == player.robot.nq and high.tracked.scene == landing
    n = min(floor.tracked.num_frames, high.tracked.num_frames, 60)
    assert n > 10
    rise = high.tracked.qpos[:n, 2] - floor.tracked.qpos[:n, 2]
    assert np.abs(rise - 0.4).max() < 0.01
