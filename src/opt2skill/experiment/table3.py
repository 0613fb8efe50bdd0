"""`opt2skill experiment table3`: the paper's Table III (data sources and history ablation) and Fig. 3
(terrain success) as one resumable command.

1. the TO, IK and human datasets, training and held-out (another seed), matched ranges (`sources`);
2. one policy per source with the same pipeline and budget (PPO from scratch, the same steps,
   worlds, seed and history; kinematic sources train with the `pos` inputs, all they have), and TO
   policies at the other history lengths;
3. each evaluated on its source's held-out references (`eval.evaluate`), twice: as the paper's
   Table III (no randomization or noise) and under Table II's randomization and observation noise,
   the conditions the policies trained under;
4. Table III with the paper's rows and the tests of TO against each baseline (`table`), one per
   condition;
5. stair and slope sweeps of each source's policy, one success-rate figure (`figure`);
6. where everything is, provenance and the time of every step.

Policies train `--workers` at a time (`runner.train_policies_at_once`); each is evaluated, and a
data row's policy swept, as soon as its batch is trained, so that results arrive early and a later
session needs only their reports, not their policies.

Every step is marked on disk when done (`steps`), so a rerun skips it; training resumes from its
newest checkpoint, and a dataset that is gone is generated again (`sources.present`). A source
without usable references is recorded and the rest goes on.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from opt2skill.cli.console import console
from opt2skill.experiment import sources
from opt2skill.experiment.runner import (add_output, done, need, publish_table, run_experiment,
                                         train_policies_at_once, train_policy, training_note)
from opt2skill.experiment.settings import PAPER_HISTORY, SOURCE_LABELS, SOURCES, ExperimentSettings
from opt2skill.experiment.steps import DONE, Steps, Unavailable

TERRAINS = ("stairs", "slope")
COMMAND = "opt2skill experiment table3"
# The evaluation under Table II's randomization and observation noise: its steps, folders and table
# carry this suffix (`eval-to-table2`, `eval/to-table2/`, `table3-table2.md`).
TABLE_II_SUFFIX = "-table2"


def policies(s: ExperimentSettings) -> dict[str, tuple[str, int]]:
    """Row key -> (source, history) of every policy: the three data rows, then the other histories on TO."""
    rows = {source: (source, s.history) for source in SOURCES}
    rows.update({f"hist{h}": ("to", h) for h in s.histories if h != s.history})
    return rows


def run_table3(s: ExperimentSettings, out: Path, progress: bool = True) -> dict[str, Path]:
    """Run (or resume) the experiment into `out`; the paths of its outputs."""
    rows = policies(s)

    def body(out: Path, steps: Steps) -> dict[str, Path]:
        data = {(src, split): steps.run(f"data-{src}-{split}", f"{SOURCE_LABELS[src]} references ({split})",
                                        lambda src=src, split=split: sources.build(src, split, s, out, progress))
                for src in SOURCES for split in ("train", "test")}
        for batch in batches(s, rows):
            data.update(_data_present(s, out, steps, batch, progress))
            _train_at_once(s, out, batch, data, steps, progress)
            for key, (src, h) in batch.items():
                steps.run(f"train-{key}", f"train {key} ({SOURCE_LABELS[src]}, history {h})",
                          lambda key=key, src=src, h=h: _train(s, out, key, src, h, data, progress))
            for key, (src, _) in batch.items():
                steps.run(f"eval-{key}", f"evaluate {key} on held-out {SOURCE_LABELS[src]} references",
                          lambda key=key, src=src: _evaluate(s, out, key, src, steps, progress))
                steps.run(f"eval-{key}{TABLE_II_SUFFIX}", f"evaluate {key} on held-out {SOURCE_LABELS[src]} references "
                          "under Table II's randomization and noise",
                          lambda key=key, src=src: _evaluate(s, out, key, src, steps, progress, table2=True))
                for terrain in TERRAINS if key in SOURCES else ():
                    steps.run(f"sweep-{src}-{terrain}", f"{terrain} sweep of {SOURCE_LABELS[src]}",
                              lambda src=src, terrain=terrain: _sweep(s, out, src, terrain, steps, progress))
        steps.run("table3", "Table III", lambda: _table(s, out, steps))
        steps.run(f"table3{TABLE_II_SUFFIX}", "Table III under Table II's randomization and noise",
                  lambda: _table(s, out, steps, table2=True))
        steps.run("fig3", "Fig. 3 (success rate on terrain)", lambda: _figure(s, out, steps))
        return _outputs(s, out, rows, steps)

    total = 2 * len(SOURCES) + 3 * len(rows) + 2 + len(SOURCES) * len(TERRAINS) + 1
    return run_experiment(s, out, total, body)


def batches(s: ExperimentSettings, rows: dict[str, tuple[str, int]]) -> list[dict[str, tuple[str, int]]]:
    """The policies in the order of `rows`, as many at a time as train side by side (one on a GPU)."""
    size = 1 if s.device != "cpu" else max(1, s.workers or os.cpu_count() or 1)
    keys = list(rows)
    return [{key: rows[key] for key in keys[i:i + size]} for i in range(0, len(keys), size)]


def _data_present(s: ExperimentSettings, out: Path, steps: Steps, batch: dict[str, tuple[str, int]],
                  progress: bool) -> dict[tuple[str, str], dict]:
    """The data steps' records of the sources of `batch`, each dataset generated again if it is gone
    and a step of the batch that has not run yet reads it: training, evaluation and sweeps read both
    splits of their source (the training set tells which references a policy has seen)."""
    records = {}
    for source in dict.fromkeys(src for src, _ in batch.values()):
        readers = [name for key, (src, _) in batch.items() if src == source
                   for name in (f"train-{key}", f"eval-{key}", f"eval-{key}{TABLE_II_SUFFIX}")]
        readers += [f"sweep-{source}-{terrain}" for terrain in TERRAINS if source in batch]
        waiting = any(steps.record(step) is None for step in readers)
        for split in ("train", "test"):
            name = f"data-{source}-{split}"
            records[(source, split)] = (sources.present(name, source, split, s, out, steps, progress) if waiting
                                        else steps.record(name))
    return records


def eval_dir(out: Path, key: str) -> Path:
    return Path(out) / "eval" / key


def _ablation(s: ExperimentSettings, source: str) -> str:
    return s.to_ablation if source == "to" else "pos"  # kinematic records carry no torques or forces


def _train_at_once(s: ExperimentSettings, out: Path, rows: dict[str, tuple[str, int]], data, steps: Steps,
                   progress: bool) -> None:
    """The policies not trained yet whose references are there, `--workers` at a time, before the
    training steps record them."""
    jobs = [(key, data[(src, "train")]["result"], _ablation(s, src), h) for key, (src, h) in rows.items()
            if done(steps, f"train-{key}") is None and data[(src, "train")]["status"] == DONE]
    train_policies_at_once(s, out, jobs, COMMAND, progress)


def _train(s: ExperimentSettings, out: Path, key: str, source: str, history: int, data, progress: bool) -> dict:
    record = data[(source, "train")]
    if record["status"] != DONE:
        raise Unavailable(f"no training references ({record['result']['reason']})")
    return train_policy(s, out, key, record["result"], _ablation(s, source), history, COMMAND, progress)


def _evaluate(s: ExperimentSettings, out: Path, key: str, source: str, steps: Steps, progress: bool,
              table2: bool = False) -> dict:
    from opt2skill.eval.evaluate import EvalRequest, evaluate

    run = need(steps, f"train-{key}", "trained policy")["run"]
    test = need(steps, f"data-{source}-test", "held-out references")["dataset"]
    request = EvalRequest(run=Path(run), dataset=Path(test), n=s.n_test, randomize=table2, noise=table2, seed=s.seed)
    report, _ = evaluate(request, progress=progress)
    json_path, md_path = report.write(eval_dir(out, key + (TABLE_II_SUFFIX if table2 else "")))
    frames = sum(r.frames for r in report.results)
    return {"report": str(json_path), "table": str(md_path), "references": len(report.results),
            "success_rate": report.success_rate, "eval_s": report.elapsed, "frames": frames}


def _reports(s: ExperimentSettings, steps: Steps, suffix: str = "") -> tuple[dict, dict]:
    from opt2skill.eval.report import read_report

    reports, missing = {}, {}
    for key in policies(s):
        record = steps.record(f"eval-{key}{suffix}")
        if record is not None and record["status"] == DONE:
            reports[key] = read_report(Path(record["result"]["report"]))
        else:
            missing[key] = (record or {}).get("result", {}).get("reason", "not run")
    return reports, missing


def _table(s: ExperimentSettings, out: Path, steps: Steps, table2: bool = False) -> dict:
    from opt2skill.experiment.table import NOMINAL, TABLE_II as UNDER_TABLE_II, build_table

    suffix = TABLE_II_SUFFIX if table2 else ""
    reports, missing = _reports(s, steps, suffix)
    table = build_table(s.setting, reports, missing, s.histories, s.history,
                        condition=UNDER_TABLE_II if table2 else NOMINAL, stem=f"table3{suffix}")
    table.notes += _data_notes(s, steps)
    return publish_table(table, out)


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
                wanted = result.get("wanted")  # absent in folders made before the top-up
                short = (f", short of the {wanted} wanted" if wanted and c.get("accepted", 0) < wanted else "")
                notes.append(f"{SOURCE_LABELS[src]} {split}: {c.get('accepted', 0)} of {result['requested']} accepted"
                             f"{short}{why}")
            else:
                notes.append(f"{SOURCE_LABELS[src]} {split}: unavailable: {result.get('reason', 'not run')}")
    if s.human is None:
        notes.append("human-data: constructed walking clips (opt2skill.retarget.synthetic), not motion capture; "
                     "pass --human DIR for AMASS/BVH clips")
    notes.append(f"same pipeline for every policy: PPO from scratch, {s.train_steps:,} environment steps on {s.num_envs} "
                 f"worlds, seed {s.seed}, the data rows at history {s.history}{history_note(s)}{training_note(s)}; "
                 f"TO with the '{s.to_ablation}' inputs, IK and human with 'pos' "
                 "(no torques or forces in kinematic records)")
    return notes


def history_note(s: ExperimentSettings) -> str:
    """Where the data rows' history is not the paper's (its Opt2Skill row is history 10), say so."""
    return "" if s.history == PAPER_HISTORY else f" (the paper's data rows: {PAPER_HISTORY}; --history)"


def _sweep(s: ExperimentSettings, out: Path, source: str, terrain: str, steps: Steps, progress: bool) -> dict:
    from opt2skill.data.reader import Dataset
    from opt2skill.errors import ConfigError
    from opt2skill.eval.evaluate import load_run_policy
    from opt2skill.eval.sweep import SweepSettings, check_reaches_terrain, run_sweep, sweep_reference, write_sweep

    run = Path(need(steps, f"train-{source}", "trained policy")["run"])
    test = need(steps, f"data-{source}-test", "held-out references")["dataset"]
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
    add_output(outputs, steps, "table3", "Table III", "table")
    add_output(outputs, steps, f"table3{TABLE_II_SUFFIX}", "Table III under Table II", "table")
    add_output(outputs, steps, "fig3", "Fig. 3", "figure")
    for src in SOURCES:
        for split in ("train", "test"):
            add_output(outputs, steps, f"data-{src}-{split}", f"{SOURCE_LABELS[src]} references ({split})", "dataset")
    for key in rows:
        add_output(outputs, steps, f"train-{key}", f"{key} run", "run")
        add_output(outputs, steps, f"eval-{key}", f"{key} evaluation", "table")
        add_output(outputs, steps, f"eval-{key}{TABLE_II_SUFFIX}", f"{key} evaluation under Table II", "table")
    for src in SOURCES:
        for terrain in TERRAINS:
            add_output(outputs, steps, f"sweep-{src}-{terrain}", f"{src} {terrain} sweep", "table")
    return outputs
