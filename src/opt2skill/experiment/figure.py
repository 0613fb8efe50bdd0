"""Fig. 3 of the experiment: success rate against stair height and slope angle, one line per data
source, from each source's sweep (`eval.sweep`); below it, the share of trials that did not fall.

The sweep's success asks for no fall and 90 % of the reference's distance, so a policy that lags its
reference fails on flat ground without falling, and one that overshoots passes; the second row
shows the falls alone."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from opt2skill.experiment.settings import SOURCE_LABELS  # noqa: E402

AXES = {"stairs": ("step height (cm)", 100.0), "slope": ("slope angle (deg)", 1.0)}  # label, scale of the setting
STYLES = {"to": dict(marker="o", ls="-"), "ik": dict(marker="s", ls="--"), "human": dict(marker="^", ls=":")}  # equal rates stay visible


def stayed_up(result: dict[str, Any]) -> np.ndarray:
    """Percentage of each setting's trials that did not fall, in the sweep's order of settings."""
    return np.array([100.0 * np.mean([not t["fell"] for t in trials]) for trials in result["trials"].values()])


def plot_fig3(sweeps: dict[str, dict[str, dict[str, Any] | None]], path: Path, title: str) -> Path:
    """`sweeps`: terrain -> source -> the sweep's JSON (None: not run, named in the legend)."""
    path = Path(path)
    fig, axes = plt.subplots(2, len(AXES), figsize=(9, 6.4), constrained_layout=True, sharex="col")
    for column, (terrain, (xlabel, scale)) in enumerate(AXES.items()):
        for row, (ylabel, rates_of) in enumerate((
                ("success rate (%)", lambda r: 100 * np.asarray(list(r["success_rate"].values()), dtype=float)),
                ("trials without a fall (%)", stayed_up))):
            ax = axes[row, column]
            for source, result in sweeps.get(terrain, {}).items():
                if result is None:
                    ax.plot([], [], label=f"{SOURCE_LABELS[source]} (not available)")
                    continue
                values = np.asarray(result["settings"]["values"], dtype=float) * scale
                ax.plot(values, rates_of(result), lw=1.5, ms=7, mfc="none", label=SOURCE_LABELS[source],
                        **STYLES[source])
            ax.set(ylabel=ylabel, ylim=(-5, 105), title=terrain if row == 0 else None,
                   xlabel=xlabel if row == 1 else None)
            ax.grid(alpha=0.3)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=8)
    fig.suptitle(title + "\nsuccess: no fall and at least 90 % of the reference's distance", fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
