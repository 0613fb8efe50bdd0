"""The metadata an exported policy carries: everything a robot-side program needs besides the network.

Stored as one JSON document under the key `opt2skill` of the ONNX model's `metadata_props`
(docs/deploy.md has the schema). A program reading it needs nothing of the training code: joint
order, default pose, PD gains, action scale and clip, torque limits, control period, the actor's
observation layout term by term with its frames, the history specification, the reference frames
each term reads, and what produced the policy.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from opt2skill.errors import DataError

KEY = "opt2skill"
FORMAT = "opt2skill-policy"
FORMAT_VERSION = 1
INPUT, OUTPUT = "obs", "actions"


@dataclass(frozen=True)
class Term:
    name: str
    start: int
    stop: int

    @property
    def size(self) -> int:
        return self.stop - self.start


@dataclass(frozen=True)
class PolicyMetadata:
    """A parsed, checked metadata document (`raw` keeps the whole of it)."""

    raw: dict[str, Any]

    @property
    def robot(self) -> dict[str, Any]:
        return self.raw["robot"]

    @property
    def joint_names(self) -> list[str]:
        return list(self.robot["joint_names"])

    @property
    def contacts(self) -> list[str]:
        """The references' contacts the policy observes forces at, in its order (metadata written before
        contacts beyond the feet has none: the robot's feet then)."""
        return list(self.robot.get("contacts", self.robot["feet"]))

    @property
    def nu(self) -> int:
        return len(self.robot["joint_names"])

    def array(self, key: str) -> np.ndarray:
        return np.asarray(self.robot[key], dtype=float)

    @property
    def control(self) -> dict[str, Any]:
        return self.raw["control"]

    @property
    def observation(self) -> dict[str, Any]:
        return self.raw["observation"]

    @property
    def terms(self) -> list[Term]:
        return [Term(t["name"], int(t["start"]), int(t["stop"])) for t in self.observation["terms"]]

    @property
    def obs_dim(self) -> int:
        return int(self.observation["dim"])

    @property
    def history(self) -> dict[str, Any]:
        return self.observation["history"]

    @property
    def reference(self) -> dict[str, Any]:
        return self.observation["reference"]

    @property
    def task(self) -> dict[str, Any]:
        return self.raw["task"]

    @property
    def training(self) -> dict[str, Any]:
        return self.raw["training"]


REQUIRED = {
    "robot": ("name", "hash", "joint_names", "default_pose", "kp", "kd", "torque_limit", "feet"),
    "control": ("policy_dt", "action_scale", "action_clip"),
    "observation": ("dim", "terms", "history", "reference", "noise_std"),
    "action": ("dim",),
    "task": ("name", "terminations"),
    "training": ("reference_fingerprints", "provenance"),
}


def check(raw: Any, where: str) -> PolicyMetadata:
    """Parse a metadata document; a missing part or inconsistent layout is a DataError naming it."""
    if not isinstance(raw, dict) or raw.get("format") != FORMAT:
        raise DataError(f"{where}: the opt2skill metadata is not an '{FORMAT}' document")
    if raw.get("format_version") != FORMAT_VERSION:
        raise DataError(f"{where}: policy metadata version {raw.get('format_version')}; this code reads {FORMAT_VERSION}")
    for part, keys in REQUIRED.items():
        if not isinstance(raw.get(part), dict):
            raise DataError(f"{where}: the policy metadata has no '{part}' section")
        missing = [k for k in keys if k not in raw[part]]
        if missing:
            raise DataError(f"{where}: the policy metadata's '{part}' lacks {missing}")
    meta = PolicyMetadata(raw)
    nu = meta.nu
    for key in ("default_pose", "kp", "kd", "torque_limit"):
        if np.shape(meta.robot[key]) != (nu,):
            raise DataError(f"{where}: robot.{key} must have one value per joint ({nu})")
    stop = 0
    for term in meta.terms:
        if term.start != stop or term.size <= 0:
            raise DataError(f"{where}: observation term '{term.name}' is at {term.start}:{term.stop}; expected to start at {stop}")
        stop = term.stop
    if stop != meta.obs_dim:
        raise DataError(f"{where}: observation terms cover {stop} entries; the observation has {meta.obs_dim}")
    contacts = meta.contacts
    if not (isinstance(contacts, list) and all(isinstance(c, str) for c in contacts)):
        raise DataError(f"{where}: robot.contacts must be a list of end-effector names")
    force = [t for t in meta.terms if t.name == "ref_contact_force"]
    if force and force[0].size != 3 * len(contacts):
        raise DataError(f"{where}: ref_contact_force has {force[0].size} entries; the metadata lists "
                        f"{len(contacts)} contacts {contacts} (3 each)")
    if raw["action"]["dim"] != nu:
        raise DataError(f"{where}: the policy outputs {raw['action']['dim']} actions for {nu} joints")
    return meta


def read_metadata(path: str | Path) -> PolicyMetadata:
    """The metadata of an exported policy file; a clear DataError if the file is not one."""
    import onnx

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path} does not exist")
    try:
        model = onnx.load(str(path), load_external_data=False)
    except Exception as exc:  # onnx raises DecodeError and others on foreign files
        raise DataError(f"{path} is not an ONNX file: {type(exc).__name__}") from None
    props = {p.key: p.value for p in model.metadata_props}
    if KEY not in props:
        raise DataError(f"{path} has no opt2skill metadata (export policies with `opt2skill export`)")
    try:
        raw = json.loads(props[KEY])
    except json.JSONDecodeError as exc:
        raise DataError(f"{path}: the opt2skill metadata is not valid JSON: {exc}") from None
    meta = check(raw, str(path))
    inputs = {i.name: [d.dim_value or d.dim_param for d in i.type.tensor_type.shape.dim] for i in model.graph.input}
    if INPUT not in inputs or inputs[INPUT][-1] != meta.obs_dim:
        raise DataError(f"{path}: the network's input '{INPUT}' does not take the {meta.obs_dim} observations its metadata describes")
    outputs = [[d.dim_value or d.dim_param for d in o.type.tensor_type.shape.dim] for o in model.graph.output]
    if len(outputs) != 1 or not outputs[0] or not (outputs[0][-1] == meta.nu or isinstance(outputs[0][-1], str)):
        # (a str: a size the file leaves open; the player runs the network once to check it)
        shown = [shape[-1] if shape else "?" for shape in outputs]
        raise DataError(f"{path}: the network outputs {shown} values; its metadata describes {meta.nu} actions "
                        "(one per joint)")
    return meta


def file_digest(path: str | Path) -> str:
    """SHA-256 of a file: identifies an exported policy in reports."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
