"""Fig. 3 of the experiment: success rate against stair height and slope angle, one line per data
source, from each source's sweep (`eval.sweep`)."""

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


def plot_fig3(sweeps: dict[str, dict[str, dict[str, Any] | None]], path: Path, title: str) -> Path:
    """`sweeps`: terrain -> source -> the sweep's JSON (None: not run, named in the legend)."""
    path = Path(path)
    fig, axes = plt.subplots(1, len(AXES), figsize=(9, 3.6), constrained_layout=True)
    for ax, (terrain, (xlabel, scale)) in zip(axes, AXES.items()):
        for source, result in sweeps.get(terrain, {}).items():
            if result is None:
                ax.plot([], [], label=f"{SOURCE_LABELS[source]} (not available)")
                continue
            values = np.asarray(result["settings"]["values"], dtype=float) * scale
            rates = 100 * np.asarray(list(result["success_rate"].values()), dtype=float)
            ax.plot(values, rates, lw=1.5, ms=7, mfc="none", label=SOURCE_LABELS[source], **STYLES[source])
        ax.set(xlabel=xlabel, ylabel="success rate (%)", ylim=(-5, 105), title=terrain)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
