"""`opt2skill export`: a run's actor as an ONNX file with the observation normalization folded into
its first layer, and the metadata a robot-side program needs (`deploy.metadata`).

The network is written with the `onnx` library's graph helpers, layer by layer from the trained
torch modules: Gemm for each linear layer, the activation's own ONNX operator. Folding: the actor
computes W (x - m) / (s + eps) + b; the file holds W' = W / (s + eps) and b' = b - W' m, computed
in float64 and stored as float32, so it takes the raw observation. `tests/test_deploy_export.py`
compares onnxruntime with the torch actor on observations of real rollouts.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper

from opt2skill.data.atomic import atomic_path, dumps
from opt2skill.data.record import FRAME_DT
from opt2skill.deploy.metadata import FORMAT, FORMAT_VERSION, INPUT, KEY, OUTPUT, PolicyMetadata, check
from opt2skill.deploy.observations import DYNAMIC, KINEMATIC, TERMS
from opt2skill.envs import layout
from opt2skill.errors import ConfigError, DataError
from opt2skill.eval.evaluate import RunPolicy, load_run_policy, training_fingerprints
from opt2skill.provenance import provenance
from opt2skill.rl.run import read_run

OPSET = 17
TRAINING_PHYSICS_DT = 0.001  # s, the training simulator's physics step (docs/conventions.md)


def export_policy(run: Path, out: Path, checkpoint: Path | None = None) -> tuple[Path, PolicyMetadata]:
    """Write the run's actor (newest checkpoint unless given) to `out` as ONNX with metadata."""
    out = Path(out)
    if out.suffix != ".onnx":
        raise ConfigError(f"--out must name a .onnx file, got {out}")
    source = load_run_policy(run, checkpoint)
    meta = check(json.loads(dumps(metadata(source, Path(run)))), str(out))  # exactly what the file will hold
    model = actor_graph(source.policy.module, meta.obs_dim)
    onnx.checker.check_model(model)
    model.metadata_props.add(key=KEY, value=dumps(meta.raw))
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        onnx.save(model, str(tmp))
    return out, meta


def actor_graph(module: torch.nn.Module, obs_dim: int) -> onnx.ModelProto:
    """ONNX graph of rsl_rl's exportable actor (normalizer, MLP, deterministic output), normalizer folded."""
    if type(module.deterministic_output).__name__ not in ("_IdentityDeterministicOutput", "Identity"):
        raise ConfigError(f"export supports actors whose action is the MLP output (Gaussian policies); this one "
                          f"ends with {type(module.deterministic_output).__name__}")
    mean, scale = _normalizer(module.obs_normalizer, obs_dim)
    nodes, weights, x = [], [], INPUT
    layers = list(module.mlp)
    linear = [i for i, layer in enumerate(layers) if isinstance(layer, torch.nn.Linear)]
    for i, layer in enumerate(layers):
        y = OUTPUT if i == len(layers) - 1 else f"h{i}"
        if isinstance(layer, torch.nn.Linear):
            w = layer.weight.detach().double().numpy()
            b = layer.bias.detach().double().numpy()
            if i == linear[0]:
                w = w / scale  # fold (x - mean) / scale into the first layer
                b = b - w @ mean
            weights += [numpy_helper.from_array(w.astype(np.float32), f"W{i}"),
                        numpy_helper.from_array(b.astype(np.float32), f"b{i}")]
            nodes.append(helper.make_node("Gemm", [x, f"W{i}", f"b{i}"], [y], transB=1))
        else:
            nodes.append(_activation(layer, x, y))
        x = y
    if x != OUTPUT:
        raise ConfigError("the actor's MLP must end with a linear layer")
    graph = helper.make_graph(
        nodes, "opt2skill_actor",
        [helper.make_tensor_value_info(INPUT, TensorProto.FLOAT, ["batch", obs_dim])],
        [helper.make_tensor_value_info(OUTPUT, TensorProto.FLOAT, ["batch", layers[linear[-1]].out_features])],
        weights,
    )
    model = helper.make_model(graph, producer_name="opt2skill", opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8  # readable by onnxruntime releases of the last years
    return model


def _normalizer(norm: torch.nn.Module, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, divisor) of the observation normalizer: x_normalized = (x - mean) / divisor."""
    if isinstance(norm, torch.nn.Identity):
        return np.zeros(dim), np.ones(dim)
    try:
        mean = norm._mean.detach().double().numpy().reshape(-1)
        divisor = norm._std.detach().double().numpy().reshape(-1) + float(norm.eps)
    except AttributeError:
        raise ConfigError(f"unknown observation normalizer {type(norm).__name__}") from None
    return mean, divisor


def _activation(layer: torch.nn.Module, x: str, y: str) -> onnx.NodeProto:
    if isinstance(layer, torch.nn.ELU):
        return helper.make_node("Elu", [x], [y], alpha=float(layer.alpha))
    if isinstance(layer, torch.nn.ReLU):
        return helper.make_node("Relu", [x], [y])
    if isinstance(layer, torch.nn.Tanh):
        return helper.make_node("Tanh", [x], [y])
    if isinstance(layer, torch.nn.Sigmoid):
        return helper.make_node("Sigmoid", [x], [y])
    if isinstance(layer, torch.nn.LeakyReLU):
        return helper.make_node("LeakyRelu", [x], [y], alpha=float(layer.negative_slope))
    raise ConfigError(f"export does not know the activation {type(layer).__name__} (elu, relu, tanh, sigmoid, leaky_relu)")


def metadata(source: RunPolicy, run: Path) -> dict[str, Any]:
    """The metadata document (docs/deploy.md) of a run's policy."""
    spec, robot, cfg = source.spec, source.robot, source.robot.config
    tracking = spec.tracking
    obs = tracking.observations
    contacts = spec.contact_names(robot)
    actor = layout(obs, robot.nu, len(contacts)).actor
    unknown = [name for name in actor if name not in TERMS]
    if unknown:
        raise DataError(f"the policy observes {unknown}, which the standalone player cannot build")
    fingerprints = training_fingerprints(spec, run)
    invocations = read_run(run).get("invocations", [])
    return {
        "format": FORMAT, "format_version": FORMAT_VERSION,
        "robot": {"name": robot.name, "hash": robot.hash, "joint_names": cfg.joint_names,
                  "default_pose": cfg.default_pose.tolist(), "kp": (cfg.kp * tracking.actions.kp_scale).tolist(), "kd": cfg.kd.tolist(),
                  "torque_limit": cfg.torque_limit.tolist(), "velocity_limit": cfg.velocity_limit.tolist(),
                  "feet": [f.name for f in cfg.feet], "contacts": list(contacts)},
        "control": {
            "policy_dt": FRAME_DT, "training_physics_dt": TRAINING_PHYSICS_DT,
            "action_scale": tracking.actions.scale, "action_clip": tracking.actions.clip,
            "pd_law": "target = default_pose + action_scale * clip(action, -action_clip, action_clip); "
                      "u = clip(kp (target - q) - kd qd, -torque_limit, torque_limit), at every physics step",
        },
        "observation": {
            "input": INPUT, "dim": max(s.stop for s in actor.values()), "dtype": "float32",
            "normalization": "folded into the first layer: the network takes raw observations",
            "terms": [{"name": name, "start": s.start, "stop": s.stop, "size": s.stop - s.start, "meaning": TERMS[name]}
                      for name, s in actor.items()],
            "history": {"samples": obs.history, "stride": obs.stride, "order": "newest first",
                        "joint_pos": "[q_t, q_{t-stride}, ..., q_{t-(N-1) stride}], each reading noisy on its own",
                        "action": "[a_{t-1}, a_{t-1-stride}, ..., a_{t-1-(N-1) stride}] (clipped actions)",
                        "reset": "at an episode start both histories are filled: joint positions with the start "
                                 "reading, actions with (q_start - default_pose) / action_scale"},
            "reference": {"offset": obs.reference_offset, "kinematic_terms": [t for t in KINEMATIC if t in actor],
                          "dynamic_terms": [t for t in DYNAMIC if t in actor],
                          "rule": "at policy step t (reference frame t = now), kinematic terms read frame "
                                  "t + offset (clamped to the last frame), dynamic terms frame t"},
            "noise_std": dataclasses.asdict(obs.noise),
        },
        "action": {"output": OUTPUT, "dim": robot.nu},
        "task": {"name": tracking.task, "ablation": tracking.ablation,
                 "terminations": dataclasses.asdict(tracking.terminations)},
        "training": {
            "run": source.info["run"], "checkpoint": source.info["checkpoint"], "iteration": source.info["iteration"],
            "env_steps": source.info["env_steps"], "dataset": spec.dataset, "dataset_identity": spec.dataset_identity,
            "trajectories": spec.trajectories, "seed": spec.seed, "num_envs": spec.num_envs,
            "reference_fingerprints": fingerprints if fingerprints is not None else None,
            "ppo": dataclasses.asdict(spec.ppo), "tracking": json.loads(dumps(dataclasses.asdict(tracking))),
            "provenance": invocations[-1].get("provenance", {}) if invocations else {},
            "export_provenance": provenance(robot.hash, command="export"),
        },
    }
