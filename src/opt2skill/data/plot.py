"""One trajectory on one page (PNG): paths, heights, torques, contact forces with the schedule."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from opt2skill.data.record import Trajectory  # noqa: E402
from opt2skill.robots import RobotConfig  # noqa: E402


def _shade(ax, time: np.ndarray, active: np.ndarray, color, label: str | None = None) -> None:
    """Shade the intervals where `active` is true."""
    edges = np.diff(np.concatenate([[0], active.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    dt = time[1] - time[0] if len(time) > 1 else 0.0
    for i, (a, b) in enumerate(zip(starts, stops)):
        ax.axvspan(time[a], time[b - 1] + dt, color=color, alpha=0.12, lw=0, label=label if i == 0 else None)


def _names_in(traj: Trajectory, prefix: str) -> list[int]:
    return [i for i, name in enumerate(traj.ee_names) if name.endswith(prefix)]


def plot_trajectory(traj: Trajectory, path: str | Path, title: str = "", robot_config: RobotConfig | None = None) -> Path:
    """Write the page to `path`. With the robot's config, joints are named and split legs / arms."""
    path = Path(path)
    t = traj.time
    feet = _names_in(traj, "_foot")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig, axes = plt.subplots(3, 2, figsize=(14, 12), constrained_layout=True)

    ax = axes[0, 0]
    ax.plot(traj.qpos[:, 0], traj.qpos[:, 1], color="k", lw=1.5, label="base")
    ax.plot(traj.com[:, 0], traj.com[:, 1], color="gray", lw=1, ls="--", label="CoM")
    for j, e in enumerate(feet):
        ax.plot(traj.ee_pos[:, e, 0], traj.ee_pos[:, e, 1], color=colors[j], lw=1, label=traj.ee_names[e])
        if traj.ee_names[e] in traj.contact_names:
            c = traj.contact_names.index(traj.ee_names[e])
            stance = traj.contact_active[:, c]
            ax.plot(traj.ee_pos[stance, e, 0], traj.ee_pos[stance, e, 1], ".", ms=3, color=colors[j])
    ax.set(title="top view (dots: stance)", xlabel="x (m)", ylabel="y (m)")
    spans = np.ptp(traj.ee_pos[:, feet, :2].reshape(-1, 2), axis=0) if feet else np.ones(2)
    if spans.max() < 4 * max(spans.min(), 0.05):  # equal axes unless that squashes a long walk flat
        ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=8)

    ax = axes[0, 1]
    ax.plot(t, traj.qpos[:, 2], color="k", label="base z")
    ax.plot(t, traj.com[:, 2], color="gray", ls="--", label="CoM z")
    for j, e in enumerate(feet):
        ax.plot(t, traj.ee_pos[:, e, 2], color=colors[j], label=f"{traj.ee_names[e]} z")
    ax.set(title="heights", xlabel="time (s)", ylabel="z (m)")
    ax.legend(fontsize=8, ncol=2)

    nu = traj.joint_torque.shape[1]
    if robot_config is not None:
        names = robot_config.joint_names
        legs = sorted(names.index(j) for g, js in robot_config.joint_groups.items() if "leg" in g for j in js)
    else:
        names, legs = [f"joint {i}" for i in range(nu)], list(range(nu))
    arms = [i for i in range(nu) if i not in legs]
    for ax, group, label in ((axes[1, 0], legs, "leg"), (axes[1, 1], arms, "arm")):
        # One colour per joint kind, solid for the left side, dashed for the right.
        kinds = list(dict.fromkeys(n.removeprefix("left_").removeprefix("right_") for n in (names[i] for i in group)))
        for i in group:
            kind = names[i].removeprefix("left_").removeprefix("right_")
            style = "--" if names[i].startswith("right_") else "-"
            ax.plot(t, traj.joint_torque[:, i], lw=0.8, ls=style, color=colors[kinds.index(kind) % len(colors)], label=names[i])
        side = " (solid left, dashed right)" if any(names[i].startswith("right_") for i in group) else ""
        ax.set(title=(f"{label} joint torques" if arms else "joint torques") + side, xlabel="time (s)", ylabel="N m")
        if group:
            ax.legend(fontsize=6, ncol=4, framealpha=0.6)

    ax = axes[2, 0]
    for c, name in enumerate(traj.contact_names):
        _shade(ax, t, traj.contact_active[:, c], colors[c % len(colors)], f"{name} active")
        ax.plot(t, traj.contact_wrench[:, c, 2], color=colors[c % len(colors)], label=f"{name} f_z")
        tangential = np.linalg.norm(traj.contact_wrench[:, c, :2], axis=1)
        ax.plot(t, tangential, color=colors[c % len(colors)], ls=":", lw=0.8, label=f"{name} |f_xy|")
    ax.set(title="contact forces (shaded: contact schedule)", xlabel="time (s)", ylabel="N")
    ax.legend(fontsize=7, ncol=2, framealpha=0.6)

    ax = axes[2, 1]
    for i, label in enumerate(("v_x", "v_y", "v_z")):
        ax.plot(t, traj.base_lin_vel[:, i], label=f"{label} (m/s)")
    ax.plot(t, traj.base_ang_vel[:, 2], label="yaw rate (rad/s)", ls="--")
    ax.set(title="base velocity, body frame", xlabel="time (s)")
    ax.legend(fontsize=8)

    params = ", ".join(f"{k}={v:.3g}" for k, v in traj.params.items())
    v = traj.validation
    verdict = "" if not v else ("accepted" if v.get("accepted") else "rejected: " + ", ".join(v.get("reasons", [])))
    fig.suptitle(f"{title}  {traj.task} on {traj.robot}, {traj.duration:.2f} s\n{params}   {verdict}".strip())
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
