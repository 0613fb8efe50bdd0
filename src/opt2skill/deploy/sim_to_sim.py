"""`opt2skill deploy-sim`: the standalone player on held-out references, measured like `opt2skill eval`.

The report has the same tables as `eval`'s, so the sim-to-sim gap (training simulator at 1 kHz
against this player at 2 kHz with its own observation code, latency and sensor noise) is the
difference of two rows. References the policy trained on are known from the fingerprints in its
metadata.
"""

from __future__ import annotations

import time
from pathlib import Path

from opt2skill.data.reader import Dataset
from opt2skill.deploy.metadata import file_digest
from opt2skill.deploy.player import Player, PlayerConfig, PlayerRollout
from opt2skill.errors import DataError
from opt2skill.eval.metrics import tracking_errors
from opt2skill.eval.references import check_metric_fields, select_references
from opt2skill.eval.report import EvalReport, TrajectoryResult
from opt2skill.eval.task_metrics import task_metrics
from opt2skill.provenance import provenance


def deploy_sim(onnx_path: Path, dataset_dir: Path, n: int = 20, split: str = "held-out", indices: tuple[int, ...] = (),
               config: PlayerConfig = PlayerConfig(), progress: bool = True) -> tuple[EvalReport, list[PlayerRollout]]:
    player = Player(onnx_path, config)
    meta = player.meta
    dataset = Dataset.open(dataset_dir)
    if dataset.identity.get("robot_hash") not in (None, player.robot.hash):
        raise DataError(f"dataset {dataset_dir} was made for another robot file than the policy {onnx_path}")
    refs = select_references(dataset, meta.training["reference_fingerprints"], n, split, list(indices),
                             what=f"the policy {onnx_path}")
    check_metric_fields(dataset, meta.task["name"], refs.positions[0], player.contacts)
    references = [dataset[p] for p in refs.positions]
    from tqdm import tqdm

    start = time.perf_counter()
    rollouts = []
    with tqdm(total=sum(t.num_frames - 1 for t in references), disable=not progress, unit="step", unit_scale=True,
              desc="2 kHz player", dynamic_ncols=True, leave=False) as bar:
        for reference in references:
            rollouts.append(player.run(reference))
            bar.update(reference.num_frames - 1)
    results = [TrajectoryResult(index, r.reference.params, seen, r.cause, r.tracked.num_frames, r.reference.num_frames,
                                tracking_errors(r.reference, r.tracked, fell=r.fell), task_metrics(r.reference, r.tracked))
               for r, index, seen in zip(rollouts, refs.indices, refs.seen)]
    training = meta.training
    name = f"{Path(onnx_path).name} (player, {1 / config.physics_dt:.0f} Hz PD)"
    info = {
        "name": name, "onnx": str(Path(onnx_path).resolve()), "run": training.get("run"),
        "iteration": training.get("iteration"), "env_steps": training.get("env_steps"), "task": meta.task["name"],
        "key": {"sha256": file_digest(onnx_path)},
        "description": f"{Path(onnx_path).resolve()} (run {training.get('run')}, iteration {training.get('iteration')}), "
                       f"standalone player: PD at {1 / config.physics_dt:.0f} Hz, policy at {1 / player.policy_dt:.0f} Hz, "
                       f"extra latency {1000 * config.latency:g} ms, sensor noise x{config.noise:g}",
    }
    options = {"physics_dt": config.physics_dt, "substeps": player.substeps, "latency": config.latency,
               "noise": config.noise, "seed": config.seed}
    report = EvalReport("deploy-sim", info, refs.to_dict(), options, results, time.perf_counter() - start,
                        provenance(player.robot.hash, command="deploy-sim", onnx=info["onnx"]))
    return report, rollouts
