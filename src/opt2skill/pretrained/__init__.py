"""Policies shipped in the package (`--pretrained NAME` of eval, play, sweep, export and deploy-sim).

A shipped policy is a small run directory inside the package, readable by everything that reads
runs, with nothing a user's command writes into it:

    pretrained/NAME/run.json                    the run's identity (task config, PPO config, robot
                                                hash, dataset identity) and how it was trained
    pretrained/NAME/best/model.pt               the actor (normalizer included), nothing else
    pretrained/NAME/training_fingerprints.json  the references it trained on (task + parameters), so
                                                that evaluations know which references are held out
    pretrained/NAME/policy.onnx                 the same actor as ONNX with its metadata
    pretrained/NAME/report/*                    its evaluation on held-out references when shipped
    pretrained/NAME/MANIFEST.json               sha256 of every file above, and the provenance

`pretrained_run(NAME)` checks every file against the manifest first: a modified or missing file is
an error naming it, never a silently different policy.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any

from opt2skill.data.atomic import write_json
from opt2skill.errors import ConfigError, DataError

ROOT = Path(__file__).parent
MANIFEST = "MANIFEST.json"
FINGERPRINTS = "training_fingerprints.json"
ONNX = "policy.onnx"
FORMAT = "opt2skill-pretrained"
FORMAT_VERSION = 1


def names(root: Path = ROOT) -> list[str]:
    return sorted(p.parent.name for p in Path(root).glob(f"*/{MANIFEST}"))


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_manifest(name: str, root: Path = ROOT) -> dict[str, Any]:
    known = names(root)
    if name not in known:
        raise ConfigError(f"unknown pretrained policy '{name}'; shipped: {', '.join(known) or 'none'}")
    path = Path(root) / name / MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(f"pretrained policy '{name}': {path} is unreadable ({exc}); reinstall opt2skill") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT or not isinstance(manifest.get("files"), dict):
        raise DataError(f"pretrained policy '{name}': {path} is not an opt2skill manifest; reinstall opt2skill")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise DataError(f"pretrained policy '{name}' has manifest version {manifest.get('format_version')}; this code "
                        f"reads {FORMAT_VERSION}")
    return manifest


def pretrained_run(name: str, root: Path = ROOT) -> Path:
    """The run directory of the shipped policy `name`, every file checked against its manifest."""
    manifest = read_manifest(name, root)
    directory = Path(root) / name
    for relative, expected in manifest["files"].items():
        path = directory / relative
        if not path.is_file():
            raise DataError(f"pretrained policy '{name}': {path} is missing; reinstall opt2skill")
        found = sha256(path)
        if found != expected:
            raise DataError(f"pretrained policy '{name}': {path} was modified (sha256 {found[:12]}, shipped "
                            f"{expected[:12]}); reinstall opt2skill")
    return directory


def pretrained_onnx(name: str, root: Path = ROOT) -> Path:
    return pretrained_run(name, root) / ONNX


def pack(run: Path, name: str, root: Path = ROOT, checkpoint: Path | None = None,
         reports: tuple[Path, ...] = (), note: str = "") -> Path:
    """Ship the policy of `run` (its `best` unless `checkpoint` is given) as `root/name`: the actor
    alone, the run's identity, the references it trained on, the ONNX export, the given report files
    and a manifest of hashes. Replaces an earlier `root/name`."""
    from opt2skill.deploy.export import export_policy
    from opt2skill.eval.evaluate import load_run_policy, training_fingerprints
    from opt2skill.rl import checkpoint as checkpoints
    from opt2skill.rl.run import read_run

    run = Path(run)
    source = load_run_policy(run, checkpoint)
    fingerprints = training_fingerprints(source.spec, run)
    if fingerprints is None:
        raise DataError(f"run {run}'s training dataset is gone or changed: the shipped policy could not say which "
                        "references it trained on")
    target = Path(root) / name
    staging = Path(root) / f".{name}.packing"
    shutil.rmtree(staging, ignore_errors=True)
    (staging / checkpoints.BEST_DIR).mkdir(parents=True)
    written = read_run(run)
    write_json(staging / "run.json", {**written, "invocations": written.get("invocations", [])[-3:]})
    checkpoints.save_actor(Path(source.info["checkpoint"]), staging / checkpoints.BEST_DIR / "model.pt")
    write_json(staging / FINGERPRINTS, {"fingerprints": fingerprints})
    export_policy(run, staging / ONNX, Path(source.info["checkpoint"]))  # its metadata names the source run
    for report in reports:
        (staging / "report").mkdir(exist_ok=True)
        shutil.copy2(report, staging / "report" / Path(report).name)
    files = sorted(p for p in staging.rglob("*") if p.is_file())
    write_json(staging / MANIFEST, {
        "format": FORMAT, "format_version": FORMAT_VERSION, "name": name, "note": note,
        "source": {"run": str(run.resolve()), "checkpoint": source.info["checkpoint"],
                   "iteration": source.info["iteration"], "env_steps": source.info["env_steps"]},
        "files": {str(p.relative_to(staging)): sha256(p) for p in files},
    })
    shutil.rmtree(target, ignore_errors=True)
    staging.rename(target)
    return target
