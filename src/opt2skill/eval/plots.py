"""Reference against tracked motion on one page (PNG): base path, feet and hands, joint torques and
contact forces with the reference's contact schedule shaded. Dashed: reference; solid: tracked.
Same style and helpers as the dataset page (`data.plot`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from opt2skill.data.plot import _names_in, _shade  # noqa: E402
from opt2skill.data.record import Trajectory  # noqa: E402
from opt2skill.robots import RobotConfig  # noqa: E402

REF = dict(ls="--", lw=1.0)
TRK = dict(ls="-", lw=1.2)


def plot_tracking(reference: Trajectory, tracked: Trajectory, path: str | Path, title: str = "",
                  robot_config: RobotConfig | None = None) -> Path:
    """Write the page to `path`. The reference is drawn over the frames the rollout covers."""
    path = Path(path)
    n = tracked.num_frames
    t = reference.time[:n]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    feet, hands = _names_in(reference, "_foot"), _names_in(reference, "_hand")
    fig, axes = plt.subplots(3, 2, figsize=(14, 12), constrained_layout=True)

    ax = axes[0, 0]
    ax.plot(reference.qpos[:n, 0], reference.qpos[:n, 1], color="k", **REF)
    ax.plot(tracked.qpos[:, 0], tracked.qpos[:, 1], color="k", label="base", **TRK)
    for j, e in enumerate(feet):
        ax.plot(reference.ee_pos[:n, e, 0], reference.ee_pos[:n, e, 1], color=colors[j], **REF)
        ax.plot(tracked.ee_pos[:, e, 0], tracked.ee_pos[:, e, 1], color=colors[j], label=reference.ee_names[e], **TRK)
    ax.set(title="top view (dashed: reference)", xlabel="x (m)", ylabel="y (m)")
    ax.legend(fontsize=8)

    ax = axes[0, 1]
    ax.plot(t, reference.qpos[:n, 2], color="k", **REF)
    ax.plot(t, tracked.qpos[:, 2], color="k", label="base z", **TRK)
    for j, e in enumerate(feet):
        ax.plot(t, reference.ee_pos[:n, e, 2], color=colors[j], **REF)
        ax.plot(t, tracked.ee_pos[:, e, 2], color=colors[j], label=f"{reference.ee_names[e]} z", **TRK)
    ax.set(title="heights", xlabel="time (s)", ylabel="z (m)")
    ax.legend(fontsize=8)

    ax = axes[1, 0]
    for j, e in enumerate(hands):
        for k, axis in enumerate("xyz"):
            c = colors[(3 * j + k) % len(colors)]
            ax.plot(t, reference.ee_pos_base[:n, e, k], color=c, **REF)
            ax.plot(t, tracked.ee_pos_base[:, e, k], color=c, label=f"{reference.ee_names[e]} {axis}", **TRK)
    ax.set(title="hands relative to the torso (base frame)", xlabel="time (s)", ylabel="m")
    ax.legend(fontsize=7, ncol=2)

    ax = axes[1, 1]
    nu = reference.joint_torque.shape[1]
    names = robot_config.joint_names if robot_config is not None else [f"joint {i}" for i in range(nu)]
    shown = [i for i, name in enumerate(names) if name.startswith("left_") and "leg" in _group(robot_config, name)]
    for k, i in enumerate(shown or range(min(nu, 6))):
        ax.plot(t, reference.joint_torque[:n, i], color=colors[k % len(colors)], **REF)
        ax.plot(t, tracked.joint_torque[:, i], color=colors[k % len(colors)], label=names[i], **TRK)
    ax.set(title="joint torques (left leg)" if shown else "joint torques", xlabel="time (s)", ylabel="N m")
    ax.legend(fontsize=7, ncol=2)

    ax = axes[2, 0]
    for c, name in enumerate(reference.contact_names):
        color = colors[c % len(colors)]
        _shade(ax, t, reference.contact_active[:n, c], color, f"{name} scheduled")
        ax.plot(t, reference.contact_wrench[:n, c, 2], color=color, **REF)
        ax.plot(t, tracked.contact_wrench[:, c, 2], color=color, label=f"{name} f_z", **TRK)
    ax.set(title="contact normal forces (shaded: reference contact schedule)", xlabel="time (s)", ylabel="N")
    ax.legend(fontsize=7, ncol=2)

    ax = axes[2, 1]
    for k, (label, ref, trk) in enumerate((
            ("v_x (m/s)", reference.base_lin_vel[:n, 0], tracked.base_lin_vel[:, 0]),
            ("v_y (m/s)", reference.base_lin_vel[:n, 1], tracked.base_lin_vel[:, 1]),
            ("yaw rate (rad/s)", reference.base_ang_vel[:n, 2], tracked.base_ang_vel[:, 2]))):
        ax.plot(t, ref, color=colors[k], **REF)
        ax.plot(t, trk, color=colors[k], label=label, **TRK)
    ax.set(title="base velocity, body frame", xlabel="time (s)")
    ax.legend(fontsize=8)

    ended = "" if n == reference.num_frames else f", tracked {t[-1]:.2f} of {reference.duration:.2f} s"
    params = ", ".join(f"{k}={v:.3g}" for k, v in reference.params.items())
    fig.suptitle(f"{title}{ended}\n{params}".strip())
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _group(config: RobotConfig | None, joint: str) -> str:
    if config is None:
        return ""
    return next((g for g, joints in config.joint_groups.items() if joint in joints), "")


def plot_success(settings: np.ndarray, rates: np.ndarray, path: str | Path, xlabel: str, title: str,
                 label: str = "policy") -> Path:
    """Success rate against a terrain setting (the paper's Fig. 3 style)."""
    path = Path(path)
    fig, ax = plt.subplots(figsize=(5, 3.6), constrained_layout=True)
    ax.plot(settings, 100 * np.asarray(rates), "o-", lw=1.5, label=label)
    ax.set(xlabel=xlabel, ylabel="success rate (%)", ylim=(-5, 105), title=title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
