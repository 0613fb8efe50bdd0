"""`opt2skill experiment table4`: the paper's Table IV (force and torque inputs in a wiping task,
Sec. IV-F), Fig. 4 (contact-force profiles) and the desk-height transfer as one resumable command.

1. the wiping datasets (`force_sets`): training (force and desk height sampled), one held-out set
   per force level (force pinned; another seed), the transfer's reference (force and desk pinned);
2. one policy per ablation (Pos, Pos+F, Pos+T, Pos+F+T) on the one training set, identical but for
   the reference force / torque inputs and rewards (the same seed, steps, worlds and history);
3. each policy evaluated on every level's held-out set (`eval.evaluate`), with its force profiles;
4. the Pos+F+T policy on the transfer reference with the desk moved (`transfer`);
5. Table IV with the paper's figures and tests (`force_table`), Fig. 4 (`force_figure`);
6. where everything is, provenance and the time of every step (`runner`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from opt2skill.cli.console import console
from opt2skill.experiment import force_sets
from opt2skill.experiment.force_sets import level_key
from opt2skill.experiment.runner import (add_output, done, need, publish_table, run_experiment,
                                         train_policies_at_once, train_policy, training_note)
from opt2skill.experiment.steps import Steps
from opt2skill.experiment.table4_settings import ABLATION_LABELS, BEST, Table4Settings

COMMAND = force_sets.COMMAND


def run_table4(s: Table4Settings, out: Path, progress: bool = True) -> dict[str, Path]:
    """Run (or resume) the experiment into `out`; the paths of its outputs."""
    sets = force_sets.datasets(s)

    def body(out: Path, steps: Steps) -> dict[str, Path]:
        from opt2skill.experiment.table4_estimate import describe

        console.print(describe(s, sum(n for _, n in sets.values())), highlight=False, soft_wrap=True)
        for name, (wipe_set, n) in sets.items():
            steps.run(f"data-{name}", f"wiping references {name} ({n})",
                      lambda wipe_set=wipe_set, n=n: force_sets.build(wipe_set, n, s, out, progress))
        _train_at_once(s, out, steps, progress)
        for a in s.ablations:
            steps.run(f"train-{a}", f"train {ABLATION_LABELS[a]}",
                      lambda a=a: train_policy(s, out, a, data_result(s, steps, "train"), a, s.history, COMMAND, progress))
        for a in s.ablations:
            for f in s.forces:
                steps.run(f"eval-{a}-{level_key(f)}", f"evaluate {ABLATION_LABELS[a]} at {f:g} N",
                          lambda a=a, f=f: _evaluate(s, out, a, f, steps, progress))
        for h in s.transfer_desks:
            steps.run(f"transfer-desk{h:g}", f"{ABLATION_LABELS[BEST]} with the desk at {h:g} m",
                      lambda h=h: _transfer(s, out, h, steps))
        steps.run("table4", "Table IV", lambda: _table(s, out, steps))
        steps.run("fig4", "Fig. 4 (contact-force profiles)", lambda: _figure(s, out, steps))
        return _outputs(s, out, steps)

    total = len(sets) + len(s.ablations) * (1 + len(s.forces)) + len(s.transfer_desks) + 2
    return run_experiment(s, out, total, body)


def data_result(s: Table4Settings, steps: Steps, role: str) -> dict[str, Any]:
    """The finished dataset step of a role ("train", "f<F>", "transfer")."""
    wipe_set, _ = force_sets.roles(s)[role]
    return need(steps, f"data-{wipe_set.name}", f"{role} references")


def _train_at_once(s: Table4Settings, out: Path, steps: Steps, progress: bool) -> None:
    """The policies not trained yet, `--workers` at a time, before the training steps record them."""
    pending = [a for a in s.ablations if done(steps, f"train-{a}") is None]
    if done(steps, f"data-{force_sets.roles(s)['train'][0].name}") is None:
        return
    data = data_result(s, steps, "train")
    train_policies_at_once(s, out, [(a, data, a, s.history) for a in pending], COMMAND, progress)


def eval_dir(out: Path, ablation: str, force: float) -> Path:
    return Path(out) / "eval" / ablation / level_key(force)


def _evaluate(s: Table4Settings, out: Path, ablation: str, force: float, steps: Steps, progress: bool) -> dict:
    from opt2skill.eval.evaluate import EvalRequest, evaluate
    from opt2skill.experiment.force_figure import save_profiles

    run = need(steps, f"train-{ablation}", "trained policy")["run"]
    test = data_result(s, steps, level_key(force))["dataset"]
    report, rollouts = evaluate(EvalRequest(run=Path(run), dataset=Path(test), n=s.n_test), progress=progress)
    folder = eval_dir(out, ablation, force)
    json_path, md_path = report.write(folder)
    profiles = save_profiles(rollouts, folder / "profiles.npz")
    return {"report": str(json_path), "table": str(md_path), "profiles": str(profiles), "references": len(report.results),
            "success_rate": report.success_rate, "eval_s": report.elapsed,
            "force_error": [r.task_metrics["force_error"][0] for r in report.results]}


def _transfer(s: Table4Settings, out: Path, desk: float, steps: Steps) -> dict:
    from opt2skill.experiment.transfer import track_moved_desk

    run = need(steps, f"train-{BEST}", "trained policy")["run"]
    dataset = data_result(s, steps, "transfer")["dataset"]
    result = track_moved_desk(Path(run), Path(dataset), s.n_transfer, desk, Path(out) / "transfer" / f"desk{desk:g}")
    console.print(f"desk {desk:g} m: normal force {result['force_mean_sd'][0]:.2f} N (reference "
                  f"{result['reference_force_mean_sd'][0]:.2f} N), right hand error {result['hand_error_mean_sd'][0]:.2f} cm",
                  highlight=False)
    return {"result": str(Path(out) / "transfer" / f"desk{desk:g}" / "transfer.json"),
            "force": result["force_mean_sd"], "hand_error": result["hand_error_mean_sd"]}


def _reports(s: Table4Settings, steps: Steps):
    from opt2skill.eval.report import read_report

    reports, missing = {}, {}
    for a in s.ablations:
        for f in s.forces:
            result = done(steps, f"eval-{a}-{level_key(f)}")
            if result is not None:
                reports[a, f] = read_report(Path(result["report"]))
            else:
                record = steps.record(f"eval-{a}-{level_key(f)}") or {}
                missing[f"{ABLATION_LABELS[a]} at {f:g} N"] = record.get("result", {}).get("reason", "not run")
    return reports, missing


def _table(s: Table4Settings, out: Path, steps: Steps) -> dict:
    import json

    from opt2skill.experiment.force_table import build_table

    reports, missing = _reports(s, steps)
    table = build_table(s.setting, s.forces, s.ablations, reports, missing)
    for h in s.transfer_desks:
        result = done(steps, f"transfer-desk{h:g}")
        if result is not None:
            table.transfer.append(json.loads(Path(result["result"]).read_text()))
        else:
            table.notes.append(f"transfer to a {h:g}-m desk: not available")
    table.notes += _data_notes(s, steps)
    return publish_table(table, out)


def _data_notes(s: Table4Settings, steps: Steps) -> list[str]:
    notes = []
    for name in force_sets.datasets(s):
        result = done(steps, f"data-{name}")
        if result is not None:
            why = f" (not accepted: {result['reasons']})" if result.get("reasons") else ""
            notes.append(f"references {name}: {result['counts'].get('accepted', 0)} of {result['requested']} accepted{why}")
        else:
            reason = ((steps.record(f"data-{name}") or {}).get("result") or {}).get("reason", "not run")
            notes.append(f"references {name}: unavailable: {reason}")
    timing = f"the wipe's phases shortened to {s.timing} s" if s.timing else "the wipe task's own timing"
    first = (f"{s.distill_steps:,} environment steps distilling the optimizer's feedback expert, then PPO for"
             if s.distill_steps else "PPO from scratch for")
    notes.append(f"same pipeline for every policy on the training set: {first} {s.train_steps:,} environment "
                 f"steps on {s.num_envs} worlds, seed {s.seed}, history {s.history}{training_note(s)}; only the "
                 f"reference force / torque observations and rewards differ; {timing}")
    return notes


def _figure(s: Table4Settings, out: Path, steps: Steps) -> dict:
    from opt2skill.experiment.force_figure import load_profiles, plot_fig4

    profiles: dict[float, dict[str, list]] = {}
    for f in s.forces:
        for a in s.ablations:
            result = done(steps, f"eval-{a}-{level_key(f)}")
            profiles.setdefault(f, {})[a] = load_profiles(Path(result["profiles"])) if result else []
    title = (f"Hands' normal force on the desk, reference (dashed) and tracked (50-ms means) ({s.setting} setting, "
             f"{s.n_test} reference(s) per level and policy)")
    return {"figure": str(plot_fig4(profiles, Path(out) / "fig4.png", title))}


def _outputs(s: Table4Settings, out: Path, steps: Steps) -> dict[str, Path]:
    outputs: dict[str, Path] = {}
    add_output(outputs, steps, "table4", "Table IV", "table")
    add_output(outputs, steps, "fig4", "Fig. 4", "figure")
    for name in force_sets.datasets(s):
        add_output(outputs, steps, f"data-{name}", f"references {name}", "dataset")
    for a in s.ablations:
        add_output(outputs, steps, f"train-{a}", f"{ABLATION_LABELS[a]} run", "run")
        for f in s.forces:
            add_output(outputs, steps, f"eval-{a}-{level_key(f)}", f"{ABLATION_LABELS[a]} evaluation at {f:g} N", "table")
    for h in s.transfer_desks:
        add_output(outputs, steps, f"transfer-desk{h:g}", f"transfer, desk at {h:g} m", "result")
    return outputs
