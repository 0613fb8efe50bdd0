"""The paper's Table III as data: every row, mean ± SE as printed.

Source: Liu et al., "Opt2Skill", RA-L 2025, Table III ("Tracking performance of Opt2Skill and
baselines (Mean ± SE; lower is better)"), Sec. IV-B; 20 references per policy, evaluated in
Agility Robotics' simulator. E_pos-y and E_yaw are per step (the paper also writes "per frame").
"""

from __future__ import annotations

SOURCE = "Liu et al., Opt2Skill, RA-L 2025, Table III (tab:baseline), Sec. IV-B"

_METRICS = ("E_joint", "E_vel_x", "E_vel_yaw", "E_ee_hand", "E_ee_foot", "E_pos_x", "E_pos_y", "E_yaw")


def _row(*pairs: tuple[float, float]) -> dict[str, tuple[float, float]]:
    return dict(zip(_METRICS, pairs, strict=True))


# Keys match the experiment's rows: data sources, then history lengths on the TO data.
DATA_ROWS = {
    "to": _row((0.03, 0.01), (4.86, 4.18), (0.06, 0.04), (2.00, 0.76), (5.23, 1.75), (1.14, 0.61), (0.06, 0.03), (0.02, 0.01)),
    "human": _row((0.04, 0.03), (6.68, 8.96), (0.06, 0.08), (4.25, 3.49), (9.42, 8.19), (4.49, 7.35), (0.11, 0.18), (0.04, 0.04)),
    "ik": _row((0.02, 0.01), (7.10, 5.73), (0.06, 0.05), (5.47, 2.58), (5.24, 1.54), (2.09, 0.27), (0.10, 0.02), (0.06, 0.01)),
}
HISTORY_ROWS = {
    15: _row((0.03, 0.01), (5.93, 4.81), (0.05, 0.04), (3.11, 1.58), (6.48, 2.32), (2.49, 1.40), (0.12, 0.06), (0.05, 0.01)),
    10: _row((0.03, 0.01), (4.86, 4.18), (0.06, 0.04), (2.00, 0.76), (5.23, 1.75), (1.14, 0.61), (0.06, 0.03), (0.02, 0.01)),
    5: _row((0.04, 0.01), (6.46, 4.85), (0.06, 0.05), (5.63, 3.54), (8.59, 4.24), (1.12, 0.96), (0.06, 0.05), (0.07, 0.01)),
    0: _row((0.04, 0.02), (7.82, 5.46), (0.10, 0.09), (6.68, 4.20), (8.31, 4.60), (1.32, 0.66), (0.07, 0.04), (0.07, 0.02)),
}
# The paper reports p < 0.001 for end-effector tracking, TO against IK and against human (Sec. IV-B).
PAPER_WILCOXON = "p < 0.001 for E_ee-hand and E_ee-foot, TO against IK and against human (Sec. IV-B text)"
