"""Statistics over trajectories: mean and standard error per metric, and paired comparisons."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import mannwhitneyu, wilcoxon

from opt2skill.eval.metrics import METRICS, TrackingErrors


@dataclass(frozen=True)
class Summary:
    mean: float
    se: float  # standard error of the mean (sample std / sqrt(n)); NaN for n < 2
    n: int  # trajectories with a defined value


def summarize(errors: list[TrackingErrors]) -> dict[str, Summary]:
    """Mean and standard error of every metric over trajectories; undefined values (NaN) skipped."""
    out = {}
    for name in METRICS:
        values = np.array([getattr(e, name) for e in errors], dtype=float)
        values = values[np.isfinite(values)]
        n = len(values)
        mean = float(values.mean()) if n else float("nan")
        se = float(values.std(ddof=1) / np.sqrt(n)) if n > 1 else float("nan")
        out[name] = Summary(mean=mean, se=se, n=n)
    return out


def mean_sd(values) -> tuple[float, float]:
    """Mean and sample standard deviation of the defined values (NaN: none, or SD of fewer than two)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    mean = float(v.mean()) if len(v) else float("nan")
    return mean, float(v.std(ddof=1)) if len(v) > 1 else float("nan")


def success_rate(errors: list[TrackingErrors]) -> float:
    return float(np.mean([not e.fell for e in errors])) if errors else float("nan")


def paired_wilcoxon(a: list[TrackingErrors], b: list[TrackingErrors]) -> dict[str, float]:
    """Two-sided Wilcoxon signed-rank p-value per metric, pairing rollouts on the same references.

    NaN where fewer than two pairs are defined or where every difference is zero.
    """
    if len(a) != len(b):
        raise ValueError(f"paired comparison needs the same references: {len(a)} against {len(b)} rollouts")
    return {name: signed_rank([getattr(e, name) for e in a], [getattr(e, name) for e in b]) for name in METRICS}


def signed_rank(x, y) -> float:
    """Two-sided Wilcoxon signed-rank p-value of paired values x[i], y[i] (`scipy.stats.wilcoxon`:
    exact for small samples without ties, else the normal approximation); pairs with an undefined
    value skipped. NaN where fewer than two pairs are defined or where every difference is zero."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    keep = np.isfinite(x) & np.isfinite(y)
    if keep.sum() < 2 or np.all(x[keep] == y[keep]):
        return float("nan")
    return float(wilcoxon(x[keep], y[keep]).pvalue)


def rank_sum(a: list[TrackingErrors], b: list[TrackingErrors]) -> dict[str, float]:
    """Two-sided Wilcoxon rank-sum (Mann-Whitney U) p-value per metric, for rollouts on different
    references (nothing to pair them by). NaN where either side has fewer than two defined values."""
    p_values = {}
    for name in METRICS:
        x = np.array([getattr(e, name) for e in a], dtype=float)
        y = np.array([getattr(e, name) for e in b], dtype=float)
        x, y = x[np.isfinite(x)], y[np.isfinite(y)]
        p_values[name] = float(mannwhitneyu(x, y).pvalue) if len(x) > 1 and len(y) > 1 else float("nan")
    return p_values


def paired_difference(x, y) -> float:
    """Median of the paired differences x[i] - y[i] over the pairs both define (NaN: none): the
    direction of the signed-rank test of x against y."""
    d = np.asarray(x, dtype=float) - np.asarray(y, dtype=float)
    d = d[np.isfinite(d)]
    return float(np.median(d)) if len(d) else float("nan")


def paired_shift(a: list[TrackingErrors], b: list[TrackingErrors]) -> dict[str, float]:
    """Per metric, the median of the paired differences a - b (the signed-rank test's direction);
    NaN where no pair is defined."""
    if len(a) != len(b):
        raise ValueError(f"paired comparison needs the same references: {len(a)} against {len(b)} rollouts")
    return {name: paired_difference([getattr(x, name) for x in a], [getattr(y, name) for y in b]) for name in METRICS}


def direction(p: float, shift: float, alpha: float = 0.05) -> str:
    """"lower" or "higher" (the first side's values against the second's) where the test finds a
    difference (p < alpha) and the shift has a sign, else ""."""
    if not p < alpha or not shift == shift or shift == 0:
        return ""
    return "lower" if shift < 0 else "higher"


def median_shift(a: list[TrackingErrors], b: list[TrackingErrors]) -> dict[str, float]:
    """Per metric, median(a) - median(b) over the defined values (the rank-sum test's direction);
    NaN where either side has none."""
    out = {}
    for name in METRICS:
        x = np.array([getattr(e, name) for e in a], dtype=float)
        y = np.array([getattr(e, name) for e in b], dtype=float)
        x, y = x[np.isfinite(x)], y[np.isfinite(y)]
        out[name] = float(np.median(x) - np.median(y)) if len(x) and len(y) else float("nan")
    return out


def p_text(p: float) -> str:
    """A p-value as the tables print it: two digits, "<0.001" below that, "-" where undefined."""
    return "-" if p != p else (f"{p:.2g}" if p >= 1e-3 else "<0.001")


def p_cell(p: float, shift: float, alpha: float = 0.05) -> str:
    """`p_text` and, where the test finds a difference, its direction ("0.013 higher")."""
    way = direction(p, shift, alpha)
    return p_text(p) + (f" {way}" if way else "")
