"""The JSON summary of a dataset, derived from its recorded outcomes (so it can always be rebuilt).

Counts by status and by reason, solve/validation time and iteration statistics, parameter coverage
(histograms of the accepted parameters over the sampling ranges, with the acceptance rate per bin)
and per-figure statistics of the validation.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Any

import numpy as np

from opt2skill.data.store import ACCEPTED, FAILED, REJECTED, Outcome

COVERAGE_BINS = 10


def stats(values: list[float | None]) -> dict[str, float] | None:
    """median, p90, mean, min, max, total, count of the finite values (None when there are none)."""
    x = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    if not len(x):
        return None
    return {
        "median": float(np.median(x)),
        "p90": float(np.percentile(x, 90)),
        "mean": float(x.mean()),
        "min": float(x.min()),
        "max": float(x.max()),
        "total": float(x.sum()),
        "count": int(len(x)),
    }


def coverage(outcomes: list[Outcome], ranges: dict[str, list[float]]) -> dict[str, Any]:
    out = {}
    for name, (lo, hi) in ranges.items():
        attempted = np.array([o.params[name] for o in outcomes if name in o.params], dtype=float)
        accepted = np.array([o.params[name] for o in outcomes if o.status == ACCEPTED and name in o.params], dtype=float)
        entry: dict[str, Any] = {"range": [lo, hi]}
        if len(accepted):
            entry.update(min=float(accepted.min()), max=float(accepted.max()), mean=float(accepted.mean()))
        if hi > lo:
            edges = np.linspace(lo, hi, COVERAGE_BINS + 1)
            acc_hist = np.histogram(accepted, edges)[0]
            all_hist = np.histogram(attempted, edges)[0]
            entry["bin_edges"] = edges.tolist()
            entry["accepted_per_bin"] = acc_hist.tolist()
            entry["acceptance_per_bin"] = [float(a / t) if t else None for a, t in zip(acc_hist, all_hist)]
            entry["empty_bins"] = int((acc_hist == 0).sum())
        out[name] = entry
    return out


def figure_stats(outcomes: list[Outcome]) -> dict[str, Any]:
    """Per validation figure, over every validated trajectory: limit, max, median, failures."""
    validated = [o for o in outcomes if o.status in (ACCEPTED, REJECTED)]
    names: list[str] = []
    for o in validated:
        names += [n for n in o.figures if n not in names]
    out = {}
    for name in names:
        values = [o.figures.get(name) for o in validated]
        finite = [v for v in values if v is not None and math.isfinite(v)]
        limits = [o.limits[name] for o in validated if o.limits.get(name) is not None]
        units = [o.units[name] for o in validated if name in o.units]
        out[name] = {
            "unit": units[0] if units else "",
            "limit": limits[0] if limits else None,
            "max": max(finite) if finite else None,
            "median": float(np.median(finite)) if finite else None,
            "count": len(finite),
            "failures": sum(name in o.reasons for o in validated),
        }
    return out


def summarize(outcomes: dict[int, Outcome], identity: dict[str, Any], requested: int) -> dict[str, Any]:
    items = list(outcomes.values())
    counts = Counter(o.status for o in items)
    reasons = Counter(r for o in items if o.status != ACCEPTED for r in o.reasons)
    done = len(items)
    return {
        "task": identity.get("task"),
        "robot": identity.get("robot"),
        "seed": identity.get("seed"),
        "requested": requested,
        "done": done,
        "missing": sorted(set(range(requested)) - set(outcomes))[:100],
        "counts": {s: counts.get(s, 0) for s in (ACCEPTED, REJECTED, FAILED)},
        "acceptance_rate": counts.get(ACCEPTED, 0) / done if done else None,
        "reasons": dict(reasons.most_common()),
        "solve_time": stats([o.solve_time for o in items]),
        "validation_time": stats([o.validation_time for o in items]),
        "iterations": stats([o.iterations for o in items]),
        "coverage": coverage(items, identity.get("ranges", {})),
        "figures": figure_stats(items),
        "not_accepted": [
            {"index": o.index, "status": o.status, "reasons": o.reasons, "message": o.message, "params": o.params}
            for o in items
            if o.status != ACCEPTED
        ],
    }
