"""`opt2skill compare`: several runs on the same references, side by side (Table III style), with a
two-sided Wilcoxon signed-rank test of each run against the first, metric by metric (as the paper
compares datasets). The references are held out from every run unless asked otherwise."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from opt2skill.data.atomic import write_report_files
from opt2skill.data.reader import Dataset
from opt2skill.errors import ConfigError, DataError
from opt2skill.folder_lock import folder_lock
from opt2skill.eval.evaluate import EvalRequest, evaluate, load_run_policy, training_fingerprints
from opt2skill.eval.references import ReferenceSet, check_metric_fields, select_references
from opt2skill.eval.report import PAPER_ROWS, TABLE_III, TABLE_IV, EvalReport, header, label, mean_se
from opt2skill.eval.stats import p_cell, paired_shift, paired_wilcoxon


@dataclass
class Comparison:
    references: ReferenceSet
    reports: list[EvalReport]
    p_values: dict[str, dict[str, float]]  # "B vs A" -> metric -> p
    shifts: dict[str, dict[str, float]] = field(default_factory=dict)  # "B vs A" -> metric -> median of B - A

    def names(self) -> list[str]:
        return [r.title() for r in self.reports]

    def to_dict(self) -> dict[str, Any]:
        return {"format": "opt2skill-compare", "format_version": 1, "references": self.references.to_dict(),
                "runs": [r.to_dict() for r in self.reports], "wilcoxon_p": self.p_values,
                "median_paired_difference": self.shifts,
                "test": "two-sided Wilcoxon signed-rank, paired by reference, each run against the first"}

    def rows(self) -> list[list[str]]:
        rows = []
        for r in self.reports:
            s = r.summary()
            rows.append([r.title(), *(mean_se(s[m]) for m in (*TABLE_III, *TABLE_IV)), f"{r.success_rate:.0%}"])
        rows += [[name, *(mean_se(v.get(m)) for m in (*TABLE_III, *TABLE_IV)), "-"] for name, v in PAPER_ROWS.items()]
        return rows

    def p_rows(self) -> list[list[str]]:
        return [[pair, *(p_cell(p[m], self.shifts.get(pair, {}).get(m, float("nan"))) for m in (*TABLE_III, *TABLE_IV)), ""]
                for pair, p in self.p_values.items()]

    def markdown(self) -> str:
        head = ["run", *(header(m) for m in (*TABLE_III, *TABLE_IV)), "success"]
        lines = ["# Comparison (mean ± SE over the same references)", "", f"- references: {self.references.note}", ""]
        lines += ["| " + " | ".join(head) + " |", "|" + "|".join(" --- " for _ in head) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in self.rows()]
        lines += ["", "Wilcoxon signed-rank p-values (two-sided, paired by reference; '-' where undefined; 'lower' / "
                  "'higher': the first-named run's errors, where p < 0.05, by the median paired difference):", ""]
        p_head = ["pair", *(label(m) for m in (*TABLE_III, *TABLE_IV)), ""]
        lines += ["| " + " | ".join(p_head) + " |", "|" + "|".join(" --- " for _ in p_head) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in self.p_rows()]
        lines += ["", "The paper's row is a reference line (Agility's simulator), not a result of this code."]
        return "\n".join(lines) + "\n"

    def write(self, out: Path) -> tuple[Path, Path]:
        return write_report_files(out, "compare", self.to_dict(), self.markdown())


def compare(runs: list[Path], dataset: Path | None = None, n: int = 20, split: str = "held-out",
            indices: tuple[int, ...] = (), randomize: bool = False, noise: bool = False, seed: int = 0,
            threads: int | None = None, progress: bool = True) -> Comparison:
    """Evaluate every run on one set of references (reusing each run's cached report when its
    checkpoint, references and options are unchanged) and test each against the first."""
    if len(runs) < 2:
        raise ConfigError("compare needs at least two runs")
    loaded = [load_run_policy(r) for r in runs]
    tasks = {p.spec.tracking.task for p in loaded}
    if len(tasks) > 1:
        raise DataError(f"the runs were trained on different tasks ({', '.join(sorted(tasks))}); compare runs of one task")
    ds = Dataset.open(dataset or loaded[0].spec.dataset)
    task = tasks.pop()
    for policy in loaded:
        check_metric_fields(ds, task, contacts=policy.spec.contact_names(policy.robot))
    trained = [training_fingerprints(p.spec, p.info["run"]) for p in loaded]
    union = None if any(t is None for t in trained) else set().union(*trained)
    refs = select_references(ds, union, n, split, list(indices), what="one of the runs")
    names = [p.info["name"] for p in loaded]
    for policy in loaded:
        if names.count(policy.info["name"]) > 1:  # two runs of the same name: tell them apart
            policy.info["name"] = f"{policy.info['run']} (iteration {policy.info['iteration']})"
    reports = []
    for run, policy in zip(runs, loaded):
        request = EvalRequest(run=run, dataset=Path(ds.root), n=len(refs.indices), indices=refs.indices,
                              randomize=randomize, noise=noise, seed=seed, threads=threads)
        cache = request.default_out(policy.spec) / "eval.json"
        report, rollouts = evaluate(request, progress=progress, reuse=cache, run=policy)
        if rollouts is not None:
            _cache(report, cache.parent)
        reports.append(report)
    first = reports[0]
    pairs = {f"{r.title()} vs {first.title()}": ([x.errors for x in r.results], [x.errors for x in first.results])
             for r in reports[1:]}
    p_values = {pair: paired_wilcoxon(a, b) for pair, (a, b) in pairs.items()}
    shifts = {pair: paired_shift(a, b) for pair, (a, b) in pairs.items()}
    refs = dataclasses.replace(refs, split="held-out from every run" if split == "held-out" and not indices else refs.split)
    return Comparison(refs, reports, p_values, shifts)


def _cache(report, folder: Path) -> None:
    """Keep a run's report in its eval folder for the next comparison, under the folder's lock like
    any writer of it; a folder another command is writing (or one that cannot be written) is left
    alone: the cache only saves time."""
    try:
        with folder_lock(folder):
            report.write(folder)
    except DataError:
        pass

