"""ONNX export: onnxruntime gives the torch actor's actions on real observations, the metadata says
what the robot needs, and files that are not exported policies are refused clearly."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from eval_support import CLI, shared_run

from opt2skill.data.reader import Dataset
from opt2skill.deploy.export import actor_graph, export_policy
from opt2skill.deploy.metadata import KEY, read_metadata
from opt2skill.deploy.player import Player
from opt2skill.envs import ReferenceBank, TrackingEnv, evaluation_config, layout
from opt2skill.errors import DataError
from opt2skill.eval.evaluate import load_run_policy
from opt2skill.eval.references import dataset_fingerprints


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    run, dataset = shared_run(tmp_path_factory)
    path, meta = export_policy(run, tmp_path_factory.mktemp("export") / "policy.onnx")
    return run, dataset, path, meta


def _observations(run, dataset, steps=150):
    """Actor observations of real rollouts of the run's policy (two references, 150 steps each)."""
    source = load_run_policy(run)
    ds = Dataset.open(dataset)
    config = evaluation_config(source.spec.tracking)
    bank = ReferenceBank.from_dataset(source.robot, ds, config.observations.end_effectors, subset=[0, 1], use_cache=False)
    seen = []
    with TrackingEnv(source.robot, bank, config, 2, seed=0, threads=1) as env:
        obs, _ = env.observations()
        for _ in range(steps):
            seen.append(obs)
            obs = env.step(source.policy(obs)).actor
    return source, np.concatenate(seen)


def test_onnxruntime_gives_the_torch_actors_actions(exported):
    run, dataset, path, meta = exported
    source, obs = _observations(run, dataset)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    onnx_actions = session.run(None, {"obs": obs})[0]
    torch_actions = source.policy(obs)
    assert onnx_actions.shape == torch_actions.shape == (len(obs), 20)
    # A policy whose actions vary with its observations (forces and torques in hundreds, velocities
    # in units): a briefly trained actor's are small (its output layer starts scaled down).
    assert np.ptp(torch_actions, axis=0).max() > 1e-3
    scale = np.abs(torch_actions).max()
    np.testing.assert_allclose(onnx_actions, torch_actions, rtol=1e-5, atol=1e-5 * scale)
    # The normalization is folded in: the file is a plain MLP on raw observations (Gemm and Elu only).
    assert {n.op_type for n in onnx.load(str(path)).graph.node} == {"Gemm", "Elu"}


def test_metadata_carries_what_a_robot_side_program_needs(exported):
    run, dataset, path, meta = exported
    source = load_run_policy(run)
    cfg, tracking = source.robot.config, source.spec.tracking
    assert meta.joint_names == cfg.joint_names
    np.testing.assert_array_equal(meta.array("kp"), cfg.kp)
    np.testing.assert_array_equal(meta.array("kd"), cfg.kd)
    np.testing.assert_array_equal(meta.array("torque_limit"), cfg.torque_limit)
    np.testing.assert_array_equal(meta.array("default_pose"), cfg.default_pose)
    assert meta.control["policy_dt"] == 0.005 and meta.control["action_scale"] == tracking.actions.scale
    actor = layout(tracking.observations, source.robot.nu, 2).actor
    assert [(t.name, t.start, t.stop) for t in meta.terms] == [(k, s.start, s.stop) for k, s in actor.items()]
    assert meta.history == {**meta.history, "samples": 10, "stride": 4} and meta.reference["offset"] == 1
    assert meta.robot["hash"] == source.robot.hash and meta.task["name"] == "squat"
    assert meta.training["reference_fingerprints"] == dataset_fingerprints(Dataset.open(dataset))
    assert meta.training["iteration"] == 2 and meta.training["provenance"]["robot_hash"] == source.robot.hash
    assert read_metadata(path).raw == meta.raw


def test_files_that_are_not_exported_policies_are_refused(exported, tmp_path):
    run, dataset, path, meta = exported
    bare = tmp_path / "bare.onnx"
    onnx.save(actor_graph(load_run_policy(run).policy.module, meta.obs_dim), str(bare))
    with pytest.raises(DataError, match="has no opt2skill metadata"):
        read_metadata(bare)
    (tmp_path / "text.onnx").write_text("not a network")
    with pytest.raises(DataError, match="is not an ONNX file"):
        read_metadata(tmp_path / "text.onnx")
    model = onnx.load(str(path))
    raw = json.loads(model.metadata_props[0].value)
    raw["observation"]["terms"][2]["name"] = "lidar"
    del model.metadata_props[:]
    model.metadata_props.add(key=KEY, value=json.dumps(raw))
    onnx.save(model, str(tmp_path / "lidar.onnx"))
    with pytest.raises(DataError, match=r"terms this player does not know: \['lidar'\]"):
        Player(tmp_path / "lidar.onnx")
    del raw["robot"]["kp"]
    del model.metadata_props[:]
    model.metadata_props.add(key=KEY, value=json.dumps(raw))
    onnx.save(model, str(tmp_path / "nokp.onnx"))
    with pytest.raises(DataError, match=r"'robot' lacks \['kp'\]"):
        read_metadata(tmp_path / "nokp.onnx")
    result = subprocess.run([CLI, "deploy-sim", str(bare), "--dataset", str(dataset)], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 2 and "has no opt2skill metadata" in result.stderr and "Traceback" not in result.stderr
    result = subprocess.run([CLI, "export", str(run), "--out", str(tmp_path / "p.txt")], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 2 and "must name a .onnx file" in result.stderr
