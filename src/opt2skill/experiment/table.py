"""Table III of the experiment: each policy's mean ± SE of the eight metrics on its held-out
references, the paper's row beside it, and p-values of TO against each baseline.

Tests: TO and IK references of the same seed and index share their parameters (speed, clearance,
step timing), so their rollouts are paired by generation index and compared with the two-sided
Wilcoxon signed-rank test, as the paper does. Human references are other motions, with nothing to
pair them by: TO against human uses the two-sided Wilcoxon rank-sum (Mann-Whitney U) test. Each test
carries its direction (the median paired difference, or the difference of medians), and the table
says for each baseline whether TO is at or below it on the paper's claim metrics (`CLAIM`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from opt2skill.data.atomic import write_report_files
from opt2skill.eval.report import TABLE_III, EvalReport, header, label, mean_se
from opt2skill.eval.stats import direction, median_shift, p_cell, p_text, paired_shift, paired_wilcoxon, rank_sum
from opt2skill.experiment import paper
from opt2skill.experiment.settings import SOURCE_LABELS


@dataclass
class Row:
    key: str  # "to", "ik", "human" or "hist<N>"
    name: str
    report: EvalReport | None  # None: not available
    paper: dict[str, tuple[float, float]] | None
    missing: str = ""  # why there is no report


# The conditions of the held-out rollouts: the paper's Table III (from Agility's simulator, no
# randomization stated) and the one the policies trained under.
NOMINAL = "no randomization or observation noise"
TABLE_II = "Table II's randomization and observation noise at full strength, as in training"

# The paper's claim (Sec. IV-B) and issue 17's target: TO at or below each baseline on the end
# effectors and the drift. "Below" and "above" are two-sided p < ALPHA in the shift's direction.
CLAIM = ("E_ee_hand", "E_ee_foot", "E_pos_x", "E_pos_y", "E_yaw")
ALPHA = 0.05


@dataclass
class Table3:
    setting: str
    data_rows: list[Row]
    history_rows: list[Row]
    p_values: dict[str, dict[str, Any]] = field(default_factory=dict)  # "TO vs IK" -> {test, n, p: {metric: p}}
    notes: list[str] = field(default_factory=list)
    condition: str = NOMINAL  # of the rollouts
    stem: str = "table3"  # the files' name

    def to_dict(self) -> dict[str, Any]:
        def row(r: Row) -> dict[str, Any]:
            out: dict[str, Any] = {"key": r.key, "name": r.name, "missing": r.missing or None,
                                   "paper": {m: {"mean": v[0], "se": v[1]} for m, v in (r.paper or {}).items()}}
            if r.report is not None:
                s = r.report.summary()
                out.update(summary={m: {"mean": s[m].mean, "se": s[m].se, "n": s[m].n} for m in TABLE_III},
                           success_rate=r.report.success_rate, pace=r.report.pace_summary(),
                           turn=r.report.turn_summary(), lead=r.report.lead_summary(),
                           references=r.report.references.get("note"),
                           policy=r.report.policy.get("description"))
            return out

        return {"format": "opt2skill-table3", "format_version": 1, "setting": self.setting, "condition": self.condition,
                "data": [row(r) for r in self.data_rows], "history": [row(r) for r in self.history_rows],
                "tests": self.p_values, "paper_source": paper.SOURCE, "paper_tests": paper.PAPER_WILCOXON,
                "notes": self.notes}

    def markdown(self) -> str:
        head = ["category", "method", *(header(m) for m in TABLE_III), "success", "pace (median)",
                "lead (m/s, median)", "turns (left / right)"]
        lines = [f"# Table III ({self.setting} setting): tracking on held-out references (mean ± SE; lower is better)", "",
                 f"Rollouts with {self.condition}.", ""]
        if self.setting != "full":
            lines += [f"**A {self.setting}-setting smoke result: a few references and minutes of training. It shows "
                      "that every step runs; it is not the paper's comparison.**", ""]
        lines += ["| " + " | ".join(head) + " |", "|" + "|".join(" --- " for _ in head) + "|"]
        for category, rows in (("Data", self.data_rows), ("Ablation", self.history_rows)):
            for r in rows:
                lines.append("| " + " | ".join([category, r.name, *_cells(r)]) + " |")
                if r.paper is not None:
                    lines.append("| " + " | ".join(["", f"*paper: {r.name}*", *(f"*{mean_se(r.paper[m])}*" for m in TABLE_III),
                                                    "", "", "", ""]) + " |")
        lines += ["", f"Paper rows (italics): {paper.SOURCE}; Agility's simulator, not this code's results. Pace: the "
                  "distance covered along the reference's heading over its path length, E_pos-x with its sign (1 on "
                  "pace, above 1 ahead); lead: the same final error over the time tracked (m/s ahead of the "
                  "reference), which a slow walk's short path does not magnify as it does E_pos-x; turns: how many "
                  "references the policy ended turned left and right of (the sign of the final yaw error, E_yaw's "
                  "sign); none of the three is a paper metric.", ""]
        if self.p_values:
            p_head = ["comparison", "test", "pairs / sizes", *(label(m) for m in TABLE_III)]
            lines += ["p-values of TO against each baseline ('-' where undefined):", "",
                      "| " + " | ".join(p_head) + " |", "|" + "|".join(" --- " for _ in p_head) + "|"]
            for pair, t in self.p_values.items():
                lines.append("| " + " | ".join([pair, t["test"], t["n"], *(p_cell(t["p"][m], t.get("shift", {}).get(m, float("nan")), ALPHA) for m in TABLE_III)]) + " |")
            lines += ["", f"'lower' / 'higher': TO's errors, where p < {ALPHA:g} (the median paired difference, or "
                      f"the difference of medians, gives the direction). The paper: {paper.PAPER_WILCOXON}.", ""]
            lines += [_claim_line(pair, t) for pair, t in self.p_values.items()] + [""]
        lines += [f"- {note}" for note in self.notes]
        return "\n".join(lines) + "\n"

    def write(self, out: Path) -> tuple[Path, Path]:
        return write_report_files(out, self.stem, self.to_dict(), self.markdown())


def _cells(r: Row) -> list[str]:
    if r.report is None:
        return ["-"] * len(TABLE_III) + [f"not available: {r.missing}", "-", "-", "-"]
    s = r.report.summary()
    n = len(r.report.results)
    pace, turn, lead = r.report.pace_summary(), r.report.turn_summary(), r.report.lead_summary()
    return [*(mean_se(s[m]) for m in TABLE_III), f"{r.report.success_rate:.0%} of {n}",
            "-" if pace is None else f"{pace['median']:.2f}",
            "-" if lead is None else f"{lead['median']:+.3f}",
            "-" if turn is None else f"{turn['left']} / {turn['right']}"]


def _direction(test: dict[str, Any], metric: str) -> str:
    """"lower" or "higher" (TO's error against the baseline's, where the test finds a difference), else ""."""
    return direction(test["p"][metric], test.get("shift", {}).get(metric, float("nan")), ALPHA)


def claim(test: dict[str, Any]) -> dict[str, Any]:
    """Whether TO is at or below the baseline on every `CLAIM` metric: none significantly higher."""
    by = {d: [m for m in CLAIM if _direction(test, m) == d] for d in ("lower", "higher")}
    return {"metrics": list(CLAIM), "alpha": ALPHA, "met": not by["higher"], **by}


def _claim_line(pair: str, test: dict[str, Any]) -> str:
    c, names = claim(test), lambda ms: ", ".join(f"{label(m)} ({p_text(test['p'][m])})" for m in ms)
    baseline = pair.split(" vs ", 1)[-1]
    verdict = "**met**" if c["met"] else f"**not met**: higher on {names(c['higher'])}"
    lower = f"; lower on {names(c['lower'])}" if c["lower"] else ""
    return (f"- TO at or below {baseline} on {', '.join(label(m) for m in CLAIM)} (the paper's claim; none higher at "
            f"p < {ALPHA:g}): {verdict}{lower}.")


def build_table(setting: str, reports: dict[str, EvalReport | None], missing: dict[str, str],
                histories: tuple[int, ...], history: int, condition: str = NOMINAL, stem: str = "table3") -> Table3:
    """`reports`: "to", "ik", "human" and "hist<N>" -> the policy's report (None when unavailable),
    all rolled out under `condition`."""
    data = [Row(s, SOURCE_LABELS[s], reports.get(s), paper.DATA_ROWS.get(s), missing.get(s, "")) for s in ("to", "human", "ik")]
    hist = []
    for h in sorted(histories, reverse=True):
        key = "to" if h == history else f"hist{h}"  # the data row's policy is the ablation's row at its history
        hist.append(Row(key, f"Opt2Skill-hist{h}", reports.get(key), paper.HISTORY_ROWS.get(h), missing.get(key, "")))
    table = Table3(setting, data, hist, condition=condition, stem=stem)
    to = reports.get("to")
    for other in ("ik", "human"):
        rep = reports.get(other)
        if to is None or rep is None:
            table.notes.append(f"TO vs {SOURCE_LABELS[other]}: no test, a policy is missing")
            continue
        table.p_values[f"TO vs {SOURCE_LABELS[other]}"] = compare_reports(to, rep, paired=other == "ik")
    return table


def compare_reports(a: EvalReport, b: EvalReport, paired: bool) -> dict[str, Any]:
    """p-values of a against b: paired by generation index (the references share their parameters),
    else unpaired; each metric's shift (a's median paired difference from b, or the difference of
    medians) and the verdict on `CLAIM`."""
    if paired:
        by_index = {r.index: r for r in b.results}
        pairs = [(r, by_index[r.index]) for r in a.results if r.index in by_index]
        x, y = [x.errors for x, _ in pairs], [y.errors for _, y in pairs]
        test = {"test": "Wilcoxon signed-rank, paired by generation index",
                "n": f"{len(pairs)} pair{'' if len(pairs) == 1 else 's'}", "p": paired_wilcoxon(x, y),
                "shift": paired_shift(x, y)}
    else:
        x, y = [r.errors for r in a.results], [r.errors for r in b.results]
        test = {"test": "Wilcoxon rank-sum (Mann-Whitney U), unpaired", "n": f"{len(a.results)} vs {len(b.results)}",
                "p": rank_sum(x, y), "shift": median_shift(x, y)}
    test["claim"] = claim(test)
    return test
