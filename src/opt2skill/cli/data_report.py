"""Terminal tables for `generate` and `validate`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rich.table import Table

from opt2skill.cli.console import console, figures_table
from opt2skill.data.store import ACCEPTED, REJECTED, Outcome
from opt2skill.data.summary import figure_stats

_SHOWN = 20  # rows of failure lists


def _num(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.3g}"
    return str(value)


def validation_table(title: str, stats: dict[str, Any]) -> Table:
    table = Table(title=title, title_justify="left")
    for column, justify in (("check", "left"), ("unit", "left"), ("limit", "right"), ("max", "right"),
                            ("median", "right"), ("failures", "right")):
        table.add_column(column, justify=justify)
    for name, s in stats.items():
        table.add_row(name, s["unit"], _num(s["limit"]), _num(s["max"]), _num(s["median"]), str(s["failures"]))
    return table


def _time(stats: dict[str, float] | None) -> str:
    return "-" if not stats else f"{stats['median']:.2f} / {stats['p90']:.2f}"


def print_generation(summary: dict[str, Any], out: Path) -> None:
    counts = summary["counts"]
    rate = summary["acceptance_rate"]
    rows = [
        ("trajectories recorded / requested", f"{summary['done']} / {summary['requested']}"),
        ("accepted / rejected / failed", f"{counts['accepted']} / {counts['rejected']} / {counts['failed']}"),
        ("acceptance rate", "-" if rate is None else f"{100 * rate:.1f} %"),
        ("solve time median / p90 (s)", _time(summary["solve_time"])),
        ("validation time median / p90 (s)", _time(summary["validation_time"])),
        ("solver iterations median / p90", _time(summary["iterations"])),
    ]
    rows += [(f"reason: {reason}", str(count)) for reason, count in summary["reasons"].items()]
    console.print(figures_table(f"{summary['task']} dataset in {out}", rows))
    if summary["figures"]:
        console.print(validation_table("validation figures (accepted and rejected)", summary["figures"]))
    for item in summary["not_accepted"][:_SHOWN]:
        console.print(f"  #{item['index']} {item['status']}: {', '.join(item['reasons'])} {item['message']}".rstrip(), highlight=False)


def print_revalidation(report, directory: Path) -> None:
    outcomes = [
        Outcome(c.index, ACCEPTED if c.new["accepted"] else REJECTED, {}, list(c.new["reasons"]),
                figures=c.new["figures"], limits=c.new["limits"], units=c.new["units"])
        for c in report.checks
    ]
    console.print(validation_table(f"{directory}: {len(report.checks)} trajectories re-validated", figure_stats(outcomes)))
    if report.disagreements:
        console.print(f"[bold red]{len(report.disagreements)} figures differ from the stored ones:[/]")
        for index, name, stored, new in report.disagreements[:_SHOWN]:
            console.print(f"  #{index} {name}: stored {_num(stored)}, recomputed {_num(new)}", highlight=False)
    else:
        console.print("every recomputed figure equals the stored one")
    if report.not_recomputed:
        console.print(f"not recomputed (the feedback gains were not stored; generate with --keep-gains): "
                      f"{', '.join(sorted(report.not_recomputed))}", highlight=False)
    for index, status, reasons in report.decision_changes[:_SHOWN]:
        now = "accepted" if not reasons else "rejected (" + ", ".join(reasons) + ")"
        console.print(f"  #{index} is stored as {status}; recomputed from the file it is {now}", highlight=False)
