"""The paper's Tables III and IV as data: every row as printed (Table III mean ± SE, Table IV mean ± SD),
and the desk-height transfer figures of Sec. IV-F's text.

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

# The paper's Table IV as data: mean ± spread per reference force level (N) and the average ("avg"), 10
# references per level with desk heights in 0.85-0.95 m, Agility's simulator. The paper does not name the
# spread; the average row's (Pos: 11.7 ± 8.3 N over levels whose means run from 1.2 to 23.9 N) can only be
# a standard deviation over all references, so this experiment reports mean ± SD.
TABLE_IV_SOURCE = ("Liu et al., Opt2Skill, RA-L 2025, Table IV (tab:contactforce, 'Tracking errors under different "
                   "contact force references'), Sec. IV-F; the transfer test from the text of Sec. IV-F")
_LEVELS = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, "avg")


def _levels(*pairs: tuple[float, float]) -> dict[float | str, tuple[float, float]]:
    return dict(zip(_LEVELS, pairs, strict=True))


# Contact force tracking error (N), keys the ablations' names (envs.ABLATIONS).
FORCE_ERROR = {
    "pos": _levels((1.2, 2.1), (4.1, 1.7), (8.7, 2.2), (13.4, 2.5), (18.7, 2.4), (23.9, 2.4), (11.7, 8.3)),
    "pos_f": _levels((0.0, 0.0), (5.0, 0.4), (3.7, 2.9), (2.3, 2.4), (3.3, 3.7), (2.8, 4.3), (2.8, 3.2)),
    "pos_t": _levels((0.0, 0.0), (3.6, 1.7), (3.0, 2.6), (2.9, 3.1), (2.9, 3.8), (3.0, 4.5), (2.7, 3.2)),
    "pos_f_t": _levels((0.0, 0.0), (1.1, 1.4), (1.5, 2.2), (1.2, 2.7), (1.6, 3.4), (2.0, 3.7), (1.5, 2.6)),
}
# Right hand position tracking error (cm).
HAND_ERROR = {
    "pos": _levels((2.4, 1.7), (2.4, 1.7), (2.4, 1.7), (2.4, 1.7), (2.4, 1.7), (2.5, 1.7), (2.4, 1.7)),
    "pos_f": _levels((3.8, 2.4), (3.0, 1.5), (3.0, 1.3), (3.2, 1.4), (3.8, 1.5), (4.6, 1.7), (3.5, 1.8)),
    "pos_t": _levels((2.9, 1.5), (2.9, 1.6), (2.8, 1.7), (2.9, 1.7), (3.0, 1.6), (3.0, 1.6), (2.9, 1.6)),
    "pos_f_t": _levels((2.6, 0.8), (2.6, 0.9), (3.2, 1.4), (3.2, 1.5), (2.9, 1.3), (2.6, 1.4), (2.9, 1.3)),
}
TABLE_IV_TESTS = "p < 0.001, Wilcoxon signed-rank, Pos+F+T against each other policy, force and hand errors, all levels"
# Desk-height transfer (Sec. IV-F text): a 0.95-m, 15-N reference tracked with the desk at another
# height: the mean normal force (N) and the hand tracking error (cm), mean ± SD.
TRANSFER_REFERENCE = {"desk_height": 0.95, "force": 15.0}
TRANSFER = {0.90: {"force": (9.6, 1.5), "hand_error": (4.1, 1.6)},
            1.00: {"force": (21.3, 2.0), "hand_error": (4.5, 2.0)}}
