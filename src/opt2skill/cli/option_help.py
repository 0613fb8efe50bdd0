"""Help texts of `--set` and `--limit` that list what can be set, with ranges and defaults."""

from __future__ import annotations

from opt2skill.data.figures import FIGURES


def _unit(unit: str) -> str:
    return f" {unit}" if unit else ""


def set_help() -> str:
    from opt2skill.tasks import available_tasks, task_info

    params_of = {name: task_info(name).params for name in available_tasks() if task_info(name).params}
    tasks = [f"{task}: " + ", ".join(
        f"{p.name} in [{p.allowed[0]:g}, {p.allowed[1]:g}]{_unit(p.unit)} (default {p.default_range[0]:g}:"
        f"{p.default_range[1]:g})" for p in params) for task, params in params_of.items()]
    return "Sampling range: name=lo:hi or name=value (repeatable). Parameters, allowed range (default): " + \
        "; ".join(tasks) + "."


def limit_help(verb: str = "Validation limit or replay setting") -> str:
    judged = ", ".join(f"{name} {f.limit:g}{_unit(f.unit)}" for name, f in FIGURES.items() if f.limit is not None)
    reported = ", ".join(name for name, f in FIGURES.items() if f.limit is None)
    return (f"{verb}: name=value, 'none' to report without judging (repeatable). Limits (default): {judged}. "
            f"Reported without a limit: {reported}. Settings: cop_min_force (N), replay.<setting> (docs/data.md).")
