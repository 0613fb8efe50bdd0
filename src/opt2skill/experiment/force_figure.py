"""Fig. 4 of the experiment: the hands' normal force on the desk over time, reference against
tracked, one panel per reference force level, every policy and reference in it. Each evaluation
step stores its rollouts' profiles (`save_profiles`); the figure reads them back."""

from __future__ import annotations

import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from opt2skill.data.record import FRAME_DT, Trajectory  # noqa: E402
from opt2skill.experiment.table4_settings import ABLATION_LABELS  # noqa: E402
from opt2skill.tasks.wipe import HANDS, sensor_mean  # noqa: E402

COLORS = {"pos": "tab:red", "pos_f": "tab:orange", "pos_t": "tab:blue", "pos_f_t": "tab:green"}


def hand_normal_force(traj: Trajectory, frames: int | None = None) -> np.ndarray:
    """(frames,) the hands' summed normal force (N) on the desk: one hand presses at a time."""
    names = list(traj.contact_names)
    columns = [names.index(h) for h in HANDS]
    return traj.contact_wrench[:frames, columns, 2].sum(axis=1)


def save_profiles(rollouts, path: Path) -> Path:
    """The reference's and the tracked hands' normal force of each rollout (until its end or fall)."""
    arrays = {}
    for k, r in enumerate(rollouts):
        n = r.tracked.num_frames
        arrays[f"reference_{k}"] = hand_normal_force(r.reference)
        arrays[f"tracked_{k}"] = hand_normal_force(r.tracked, n)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    return path


def load_profiles(path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    with np.load(path) as f:
        count = sum(1 for key in f.files if key.startswith("reference_"))
        return [(f[f"reference_{k}"], f[f"tracked_{k}"]) for k in range(count)]


def plot_fig4(profiles: dict[float, dict[str, list[tuple[np.ndarray, np.ndarray]]]], path: Path, title: str) -> Path:
    """`profiles`: force level -> ablation -> [(reference, tracked) per reference] (an empty list:
    not available, named in the legend)."""
    levels = sorted(profiles)
    cols = min(3, len(levels))
    rows = -(-len(levels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False, constrained_layout=True)
    for ax, level in zip(axes.flat, levels):
        drawn_reference = False
        for ablation, runs in profiles[level].items():
            label = ABLATION_LABELS.get(ablation, ablation)
            if not runs:
                ax.plot([], [], color=COLORS.get(ablation), label=f"{label} (not available)")
                continue
            for k, (reference, tracked) in enumerate(runs):
                t = np.arange(len(tracked)) * FRAME_DT
                ax.plot(t, sensor_mean(tracked), color=COLORS.get(ablation), lw=0.9, alpha=0.8, label=label if k == 0 else None)
                if not drawn_reference:
                    ax.plot(np.arange(len(reference)) * FRAME_DT, reference, "k--", lw=1.4, label="reference",
                            zorder=10)  # over the tracked curves, which would hide it
                    drawn_reference = True
        ax.set(title=f"({'abcdefghijkl'[levels.index(level)]}) {level:g} N reference", xlabel="time (s)",
               ylabel="normal force (N)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(levels):]:
        ax.set_visible(False)
    fig.suptitle(textwrap.fill(title, 45 * cols), fontsize=9)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
