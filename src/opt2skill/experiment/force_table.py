"""Table IV of the experiment: each ablation's contact-force error (N) and right-hand position error
(cm) on the held-out wiping references of every force level and over all of them (mean ± SD), the
paper's figures beside them, the Wilcoxon signed-rank tests of Pos+F+T against each other policy,
and the desk-height transfer test.

Tests: every policy tracks the very same references (a level's set, another seed than training),
so rollouts pair by (force level, generation index), pooled over all levels, as the paper's "across
all force levels": two-sided Wilcoxon signed-rank (`eval.stats.signed_rank`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from opt2skill.data.atomic import write_report_files
from opt2skill.eval.report import EvalReport
from opt2skill.eval.stats import mean_sd, p_cell, paired_difference, signed_rank
from opt2skill.experiment import paper
from opt2skill.experiment.table4_settings import ABLATION_LABELS, BEST

# The force as a sensor sees it (50-ms means) is the table's force error, the paper's row under it; the
# same on 5-ms frames follows, with the hand's bounce on the desk in it (tasks/wipe.py `sensor_mean`).
METRICS = {"force_error": ("Force error, 50-ms means", "N", paper.FORCE_ERROR),
           "force_error_raw": ("Force error, 5-ms frames (no paper figures)", "N", {}),
           "right_hand_error": ("Right hand position error", "cm", paper.HAND_ERROR)}


@dataclass
class Table4:
    setting: str
    forces: tuple[float, ...]
    ablations: tuple[str, ...]
    cells: dict[str, dict[str, dict[str, Any]]]  # metric -> ablation -> level key ("0", ..., "avg") -> {mean, sd, n}
    missing: dict[str, str]  # "<ablation> at <F> N" -> why there is no report
    tests: dict[str, dict[str, Any]] = field(default_factory=dict)  # "Pos+F+T vs Pos" -> {pairs, p: {metric: p}}
    falls: dict[str, str] = field(default_factory=dict)  # ablation -> "k of n"
    transfer: list[dict[str, Any]] = field(default_factory=list)  # one per moved desk (transfer.track_moved_desk)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        paper_cells = {m: {a: {str(k): {"mean": v[0], "sd": v[1]} for k, v in table[a].items()} for a in table}
                       for m, (_, _, table) in METRICS.items()}
        return {"format": "opt2skill-table4", "format_version": 1, "setting": self.setting, "forces": list(self.forces),
                "ablations": list(self.ablations), "cells": self.cells, "missing": self.missing, "tests": self.tests,
                "falls": self.falls, "transfer": self.transfer, "paper": paper_cells,
                "paper_transfer": {str(h): v for h, v in paper.TRANSFER.items()}, "paper_source": paper.TABLE_IV_SOURCE,
                "paper_tests": paper.TABLE_IV_TESTS, "notes": self.notes}

    def markdown(self) -> str:
        levels = [*map(_level, self.forces), "avg"]
        head = ["policy", *(f"{f:g} N" for f in self.forces), "avg", "fell"]
        lines = [f"# Table IV ({self.setting} setting): tracking under contact-force references (mean ± SD; lower is better)", ""]
        if self.setting != "full":
            lines += [f"**A {self.setting}-setting smoke result: a few references and minutes of training. It shows "
                      "that every step runs; it is not the paper's comparison.**", ""]
        for metric, (title, unit, table) in METRICS.items():
            lines += [f"## {title} ({unit})", "", "| " + " | ".join(head) + " |", "|" + "|".join(" --- " for _ in head) + "|"]
            for a in self.ablations:
                name = ABLATION_LABELS.get(a, a)
                cells = [_cell(self.cells[metric][a].get(k)) for k in levels]
                lines.append("| " + " | ".join([name, *cells, self.falls.get(a, "-")]) + " |")
                if a in table:
                    printed = [f"*{table[a][f][0]:.1f} ± {table[a][f][1]:.1f}*" if f in table[a] else "" for f in
                               [*self.forces, "avg"]]
                    lines.append("| " + " | ".join([f"*paper: {name}*", *printed, ""]) + " |")
            lines.append("")
        lines += [f"Paper rows (italics): {paper.TABLE_IV_SOURCE}; Agility's simulator, 1400 training references, "
                  "not this code's results. 'fell': references the policy fell on (metrics up to the fall).", ""]
        if self.tests:
            best = ABLATION_LABELS[BEST]
            lines += [f"Two-sided Wilcoxon signed-rank p-values, {best} against each other policy, paired by force level "
                      "and reference over all levels ('-' where undefined):", "",
                      "| comparison | pairs | " + " | ".join(title.lower() for title, _, _ in METRICS.values()) + " |",
                      "| --- | --- |" + " --- |" * len(METRICS)]
            for pair, t in self.tests.items():
                lines.append(f"| {pair} | {t['pairs']} | " + " | ".join(p_cell(t["p"].get(m, np.nan), t.get("shift", {}).get(m, np.nan)) for m in METRICS) + " |")
            lines += ["", f"'lower' / 'higher': {best}'s errors, where p < 0.05 (the median paired difference gives "
                      f"the direction). The paper: {paper.TABLE_IV_TESTS}.", ""]
        if self.transfer:
            ref = self.transfer[0]
            lines += [f"## Desk-height transfer ({ABLATION_LABELS[BEST]})", "",
                      f"References made for a {_span_text(ref['reference_desk_height'])} m desk at "
                      f"{_span_text([r['params']['force'] for r in ref['references']])} N, tracked with the desk moved "
                      f"({len(ref['references'])} reference(s); force: the hands' mean normal force while the reference "
                      "holds its level):", "",
                      "| desk top (m) | normal force (N) | right hand error (cm) | fell | paper: force (N) | paper: hand error (cm) |",
                      "| --- | --- | --- | --- | --- | --- |"]
            for t in self.transfer:
                p = paper.TRANSFER.get(round(t["desk_height"], 2))
                fell = sum(r["fell"] for r in t["references"])
                lines.append(f"| {t['desk_height']:.2f} | {_ms(t['force_mean_sd'])} | {_ms(t['hand_error_mean_sd'])} | "
                             f"{fell} of {len(t['references'])} | "
                             + (f"*{p['force'][0]} ± {p['force'][1]}* | *{p['hand_error'][0]} ± {p['hand_error'][1]}* |"
                                if p else "| |"))
            lines.append("")
        lines += [f"- not available ('-' above): {what}: {why}" for what, why in self.missing.items()]
        lines += [f"- {note}" for note in self.notes]
        return "\n".join(lines) + "\n"

    def write(self, out: Path) -> tuple[Path, Path]:
        return write_report_files(out, "table4", self.to_dict(), self.markdown())


def _level(force: float) -> str:
    return f"{force:g}"


def _span_text(values) -> str:
    """One value, or the range of several (the transfer references' desk heights or forces)."""
    v = sorted(set(round(float(x), 3) for x in values))
    return f"{v[0]:g}" if len(v) == 1 else f"{v[0]:g} to {v[-1]:g}"


def _cell(c: dict[str, Any] | None) -> str:
    """mean ± SD; a value JSON stored as null (NaN) is undefined."""
    if c is None:
        return "-"
    mean, sd = (np.nan if c[k] is None else float(c[k]) for k in ("mean", "sd"))
    if not np.isfinite(mean):
        return "-"
    return f"{mean:.2f} ± {sd:.2f}" if np.isfinite(sd) else f"{mean:.2f} (n=1)"


def _ms(pair) -> str:
    return _cell({"mean": pair[0], "sd": pair[1]})


def _values(report: EvalReport, metric: str) -> dict[int, float]:
    return {r.index: r.task_metrics[metric][0] for r in report.results if metric in r.task_metrics}


def build_table(setting: str, forces: tuple[float, ...], ablations: tuple[str, ...],
                reports: dict[tuple[str, float], EvalReport], missing: dict[str, str]) -> Table4:
    """`reports`: (ablation, force level) -> that policy's evaluation on the level's held-out set."""
    cells: dict[str, dict[str, dict[str, Any]]] = {m: {a: {} for a in ablations} for m in METRICS}
    for metric in METRICS:
        for a in ablations:
            pooled = []
            for f in forces:
                if (a, f) in reports:
                    values = list(_values(reports[a, f], metric).values())
                    pooled += values
                    cells[metric][a][_level(f)] = _summary(values)
            cells[metric][a]["avg"] = _summary(pooled)
    table = Table4(setting, tuple(forces), tuple(ablations), cells, dict(missing))
    for a in ablations:
        results = [r for f in forces if (a, f) in reports for r in reports[a, f].results]
        table.falls[a] = f"{sum(r.fell for r in results)} of {len(results)}"
    for other in ablations:
        if other != BEST:
            table.tests[f"{ABLATION_LABELS[BEST]} vs {ABLATION_LABELS.get(other, other)}"] = compare(reports, forces, BEST, other)
    return table


def compare(reports: dict[tuple[str, float], EvalReport], forces: tuple[float, ...], a: str, b: str) -> dict[str, Any]:
    """Signed-rank p-values of ablation a against b, paired by (level, generation index), and the
    median paired difference a - b of each metric (the direction)."""
    p, shift, pairs = {}, {}, 0
    for metric in METRICS:
        x, y = [], []
        for f in forces:
            if (a, f) in reports and (b, f) in reports:
                va, vb = _values(reports[a, f], metric), _values(reports[b, f], metric)
                common = sorted(set(va) & set(vb))
                x += [va[i] for i in common]
                y += [vb[i] for i in common]
        p[metric], shift[metric] = signed_rank(x, y), paired_difference(x, y)
        pairs = len(x)
    return {"test": "Wilcoxon signed-rank, two-sided, paired by force level and generation index", "pairs": pairs, "p": p,
            "shift": shift}


def _summary(values: list[float]) -> dict[str, Any]:
    mean, sd = mean_sd(values)
    return {"mean": mean, "sd": sd, "n": int(np.isfinite(np.asarray(values, dtype=float)).sum())}
