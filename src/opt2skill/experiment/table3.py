"""`opt2skill experiment table3`: the paper's Table III (data sources and history ablation) and Fig. 3
(terrain success) as one resumable command.

1. the TO, IK and human datasets, training and held-out (another seed), matched ranges (`sources`);
2. one policy per source with the same pipeline and budget (PPO from scratch, the same steps,
   worlds, seed and history; kinematic sources train with the `pos` inputs, all they have), and TO
   policies at the other history lengths;
3. each evaluated on its source's held-out references (`eval.evaluate`);
4. Table III with the paper's rows and the tests of TO against each baseline (`table`);
5. stair and slope sweeps of each source's policy, one success-rate figure (`figure`);
6. where everything is, provenance and the time of every step.

Every step is marked on disk when done (`steps`), so a rerun skips it; training resumes from its
newest checkpoint. A source without usable references is recorded and the rest goes on.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from opt2skill.cli.console import console
from opt2skill.experiment import sources
from opt2skill.experiment.settings import SOURCE_LABELS, SOURCES, ExperimentSettings, claim_folder
from opt2skill.experiment.steps import DONE, Steps, Unavailable

TERRAINS = ("stairs", "slope")
COMMAND = "opt2skill experiment table3"


def policies(s: ExperimentSettings) -> dict[str, tuple[str, int]]:
    """Row key -> (source, history) of every policy: the three data rows, then the other histories on TO."""
    rows = {source: (source, s.history) for source in SOURCES}
    rows.update({f"hist{h}": ("to", h) for h in s.histories if h != s.history})
    return rows


def run_table3(s: ExperimentSettings, out: Path, progress: bool = True) -> dict[str, Path]:
    """Run (or resume) the experiment into `out`; the paths of its outputs."""
    from opt2skill.folder_lock import folder_lock
    from opt2skill.output_paths import check_output_dir

    s.check()
    os.environ["OMP_NUM_THREADS"] = "1"  # before Crocoddyl loads, here and in every generation worker
    out = Path(check_output_dir(out))
    rows = policies(s)
    steps = Steps(out, total=2 * len(SOURCES) + 2 * len(rows) + 1 + len(SOURCES) * len(TERRAINS) + 1)
    started = time.perf_counter()
    with folder_lock(out):
        claim_folder(out, s)  # under the lock: two runs cannot both claim an empty folder
        data = {(src, split): steps.run(f"data-{src}-{split}", f"{SOURCE_LABELS[src]} references ({split})",
                                        lambda src=src, split=split: sources.build(src, split, s, out, progress))
                for src in SOURCES for split in ("train", "test")}
        for key, (src, h) in rows.items():
            steps.run(f"train-{key}", f"train {key} ({SOURCE_LABELS[src]}, history {h})",
                      lambda key=key, src=src, h=h: _train(s, out, key, src, h, data, progress))
        for key, (src, _) in rows.items():
            steps.run(f"eval-{key}", f"evaluate {key} on held-out {SOURCE_LABELS[src]} references",
                      lambda key=key, src=src: _evaluate(s, out, key, src, steps, progress))
        steps.run("table3", "Table III", lambda: _table(s, out, steps))
        for src in SOURCES:
            for terrain in TERRAINS:
                steps.run(f"sweep-{src}-{terrain}", f"{terrain} sweep of {SOURCE_LABELS[src]}",
                          lambda src=src, terrain=terrain: _sweep(s, out, src, terrain, steps, progress))
        steps.run("fig3", "Fig. 3 (success rate on terrain)", lambda: _figure(s, out, steps))
        outputs = _outputs(s, out, rows, steps)
        _provenance(s, out, steps, time.perf_counter() - started)
    console.rule("[bold]done")
    for what, where in outputs.items():  # plain lines: a table would cut long paths
        console.print(f"{what}: {where}", soft_wrap=True, highlight=False)
    return outputs


def run_dir(out: Path, key: str) -> Path:
    return Path(out) / "runs" / key


def eval_dir(out: Path, key: str) -> Path:
    return Path(out) / "eval" / key


def _need(steps: Steps, name: str, what: str) -> dict[str, Any]:
    record = steps.record(name)
    if record is None or record["status"] != DONE:
        reason = (record or {}).get("result", {}).get("reason", "not run")
        raise Unavailable(f"no {what} ({reason})")
    return record["result"]


def _train(s: ExperimentSettings, out: Path, key: str, source: str, history: int, data, progress: bool) -> dict:
    from opt2skill.rl import session

    record = data[(source, "train")]
    if record["status"] != DONE:
        raise Unavailable(f"no training references ({record['result']['reason']})")
    ablation = s.to_ablation if source == "to" else "pos"  # kinematic records carry no torques or forces
    request = session.TrainRequest(dataset=Path(record["result"]["dataset"]), out=run_dir(out, key), steps=s.train_steps,
                                   num_envs=s.num_envs, history=history, ablation=ablation, seed=s.seed, command=COMMAND,
                                   device=s.device)
    start = time.perf_counter()
    result = session.train(request, progress=progress, announce=lambda line: console.print(line, highlight=False))
    elapsed = time.perf_counter() - start
    return {"run": str(request.out), "ablation": ablation, "history": history, "iteration": result["iteration"],
            "env_steps": result["env_steps"], "train_s": elapsed, "references": record["result"]["counts"]["accepted"]}


def _evaluate(s: ExperimentSettings, out: Path, key: str, source: str, steps: Steps, progress: bool) -> dict:
    from opt2skill.eval.evaluate import EvalRequest, evaluate

    run = _need(steps, f"train-{key}", "trained policy")["run"]
    test = _need(steps, f"data-{source}-test", "held-out references")["dataset"]
    report, _ = evaluate(EvalRequest(run=Path(run), dataset=Path(test), n=s.n_test), progress=progress)
    json_path, md_path = report.write(eval_dir(out, key))
    frames = sum(r.frames for r in report.results)
    return {"report": str(json_path), "table": str(md_path), "references": len(report.results),
            "success_rate": report.success_rate, "eval_s": report.elapsed, "frames": frames}


def _reports(s: ExperimentSettings, steps: Steps) -> tuple[dict, dict]:
    from opt2skill.eval.report import read_report

    reports, missing = {}, {}
    for key in policies(s):
        record = steps.record(f"eval-{key}")
        if record is not None and record["status"] == DONE:
            reports[key] = read_report(Path(record["result"]["report"]))
        else:
            missing[key] = (record or {}).get("result", {}).get("reason", "not run")
    return reports, missing


def _table(s: ExperimentSettings, out: Path, steps: Steps) -> dict:
    from opt2skill.experiment.table import build_table

    reports, missing = _reports(s, steps)
    table = build_table(s.setting, reports, missing, s.histories, s.history)
    table.notes += _data_notes(s, steps)
    paths = table.write(out)
    console.print(table.markdown(), highlight=False, soft_wrap=True)
    return {"json": str(paths[0]), "table": str(paths[1])}


def _data_notes(s: ExperimentSettings, steps: Steps) -> list[str]:
    """What each source's datasets hold, and anything that was not available."""
    notes = []
    for src in SOURCES:
        for split in ("train", "test"):
            record = steps.record(f"data-{src}-{split}") or {}
            result = record.get("result", {})
            if record.get("status") == DONE:
                c = result["counts"]
                why = f" (not accepted: {result['reasons']})" if result.get("reasons") else ""
                notes.append(f"{SOURCE_LABELS[src]} {split}: {c.get('accepted', 0)} of {result['requested']} accepted{why}")
            else:
                notes.append(f"{SOURCE_LABELS[src]} {split}: unavailable: {result.get('reason', 'not run')}")
    if s.human is None:
        notes.append("human-data: constructed walking clips (opt2skill.retarget.synthetic), not motion capture; "
                     "pass --human DIR for AMASS/BVH clips")
    notes.append(f"same pipeline for every policy: PPO from scratch, {s.train_steps:,} environment steps on {s.num_envs} "
                 f"worlds, seed {s.seed}; TO with the '{s.to_ablation}' inputs, IK and human with 'pos' (no torques "
                 "or forces in kinematic records)")
    return notes


def _sweep(s: ExperimentSettings, out: Path, source: str, terrain: str, steps: Steps, progress: bool) -> dict:
    from opt2skill.data.reader import Dataset
    from opt2skill.errors import ConfigError
    from opt2skill.eval.evaluate import load_run_policy
    from opt2skill.eval.sweep import SweepSettings, check_reaches_terrain, run_sweep, sweep_reference, write_sweep

    run = Path(_need(steps, f"train-{source}", "trained policy")["run"])
    test = _need(steps, f"data-{source}-test", "held-out references")["dataset"]
    values = s.stairs if terrain == "stairs" else s.slopes
    settings = SweepSettings(terrain=terrain, values=tuple(values), trials=s.sweep_trials, yaw_range=s.yaw_range,
                             start=s.sweep_start, seed=s.seed)
    policy = load_run_policy(run)
    reference, info = sweep_reference(Dataset.open(test), policy, run)
    try:
        check_reaches_terrain(reference, settings, info["description"])
    except ConfigError as exc:  # e.g. a short human clip: recorded, the other sources go on
        raise Unavailable(str(exc)) from None
    console.print(f"reference: {info['description']}", highlight=False, soft_wrap=True)
    result, _ = run_sweep(policy, reference, info, settings, progress=progress)
    paths = write_sweep(result, Path(out) / "sweeps" / f"{source}-{terrain}", SOURCE_LABELS[source])
    trial_steps = len(settings.values) * settings.trials * (reference.num_frames - 1)
    return {"sweep": str(paths[0]), "table": str(paths[1]), "plot": str(paths[2]), "sweep_s": result.elapsed,
            "world_steps": trial_steps, "success_rate": dict(zip(map(str, values), map(float, result.rates())))}


def _figure(s: ExperimentSettings, out: Path, steps: Steps) -> dict:
    from opt2skill.experiment.figure import plot_fig3

    sweeps: dict[str, dict[str, Any]] = {}
    for terrain in TERRAINS:
        for src in SOURCES:
            record = steps.record(f"sweep-{src}-{terrain}") or {}
            ok = record.get("status") == DONE
            sweeps.setdefault(terrain, {})[src] = json.loads(Path(record["result"]["sweep"]).read_text()) if ok else None
    title = (f"Success on terrain ({s.setting} setting, {s.sweep_trials} trials per setting, "
             f"yaw in ±{s.yaw_range:g}°)")
    return {"figure": str(plot_fig3(sweeps, Path(out) / "fig3.png", title))}


def _outputs(s: ExperimentSettings, out: Path, rows, steps: Steps) -> dict[str, Path]:
    outputs: dict[str, Path] = {}
    for name, what in (("table3", "Table III"), ("fig3", "Fig. 3")):
        record = steps.record(name) or {}
        if record.get("status") == DONE:
            result = record["result"]
            outputs[what] = Path(result.get("table") or result["figure"])
    for src in SOURCES:
        for split in ("train", "test"):
            record = steps.record(f"data-{src}-{split}") or {}
            if record.get("status") == DONE:
                outputs[f"{SOURCE_LABELS[src]} references ({split})"] = Path(record["result"]["dataset"])
    for key in rows:
        for step, field, what in (("train", "run", "run"), ("eval", "table", "evaluation")):
            record = steps.record(f"{step}-{key}") or {}
            if record.get("status") == DONE:
                outputs[f"{key} {what}"] = Path(record["result"][field])
    for src in SOURCES:
        for terrain in TERRAINS:
            record = steps.record(f"sweep-{src}-{terrain}") or {}
            if record.get("status") == DONE:
                outputs[f"{src} {terrain} sweep"] = Path(record["result"]["table"])
    outputs["provenance"] = Path(out) / "provenance.json"
    outputs["steps (one file per finished step)"] = Path(out) / "steps"
    return outputs


def _provenance(s: ExperimentSettings, out: Path, steps: Steps, elapsed: float) -> None:
    """Versions, robot hash, settings and every step's status and time, rewritten on every run."""
    import importlib.metadata as md

    from opt2skill.data.atomic import write_json
    from opt2skill.model import load_robot
    from opt2skill.provenance import provenance

    records = {p.stem: json.loads(p.read_text()) for p in sorted(steps.folder.glob("*.json"))}
    extra = {name: md.version(name) for name in ("scipy", "matplotlib", "mink")
             if _installed(name)}
    write_json(Path(out) / "provenance.json", {
        "experiment": "table3", "settings": s.identity(), "workers": s.workers,
        "provenance": provenance(load_robot("digit").hash, command=COMMAND, more_libraries=extra),
        "this_invocation_s": elapsed,
        "steps": {name: {"status": r["status"], "elapsed_s": r["elapsed_s"], "finished": r["finished"],
                         "reason": r["result"].get("reason")} for name, r in records.items()},
    })


def _installed(name: str) -> bool:
    import importlib.metadata as md

    try:
        md.version(name)
        return True
    except md.PackageNotFoundError:
        return False
