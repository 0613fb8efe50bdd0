"""The validation figures by name: unit, default limit, meaning (docs/data.md has the table).

A module of its own, free of heavy imports, so that the command line can list the figures in its
help without loading the physics.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Figure:
    unit: str
    limit: float | None
    help: str


# name -> unit, default limit, meaning. Order is the order of tables.
# A kinematic record (`has_dynamics=False`: IK or retargeted motion) gets only `KINEMATIC` ones.
FIGURES: dict[str, Figure] = {
    "dynamic_gap": Figure("", 1e-6, "largest gap between shooting nodes after the solve (solver statistics)"),
    "id_residual_knots_max": Figure("N, N m", 1e-3, "inverse-dynamics residual on the solver grid, largest"),
    "id_residual_knots_rms": Figure("N, N m", None, "inverse-dynamics residual on the solver grid, RMS"),
    "impulse_residual_max": Figure("N s", 1e-3, "impact-dynamics residual at impulse nodes, largest"),
    "id_residual_frames_max": Figure("N, N m", 1e-3, "inverse-dynamics residual between 200 Hz frames, largest (impact steps excluded)"),
    "id_residual_frames_rms": Figure("N, N m", None, "inverse-dynamics residual between 200 Hz frames, RMS (impact steps excluded)"),
    "friction_violation": Figure("N", 1.0, "largest |f_t| - mu f_n (or -f_n) on an active sole"),
    "cop_violation": Figure("m", 0.005, "largest distance of a centre of pressure outside its sole"),
    "inactive_contact_force": Figure("N", 1e-6, "largest force on a contact marked inactive"),
    "torque_violation": Figure("N m", 0.01, "largest |u| beyond the torque limit"),
    "joint_limit_violation": Figure("rad", 0.02, "largest joint position beyond its range"),
    "velocity_violation": Figure("rad/s", 0.5, "largest joint speed beyond the velocity limit"),
    "foot_slip": Figure("mm", 5.0, "largest sole displacement during a stance phase"),
    "foot_penetration": Figure("mm", 2.0, "deepest sole point (centre or corner) below the ground"),
    "derived_fields_error": Figure("m, m/s", 1e-6, "stored kinematic fields vs recomputed from qpos, qvel"),
    "replay_fallen_windows": Figure("fraction", 0.0, "share of replay windows (restarted from the reference) that fall"),
    "replay_joint_rms": Figure("rad", None, "joint error RMS in the replay windows, largest window"),
    "replay_base_error": Figure("m", None, "base position error in the replay windows, largest"),
    "replay_foot_error": Figure("cm", None, "sole position error in the replay windows, largest"),
    "replay_fall_time": Figure("s", None, "full-length open-loop replay: time until it falls (None: stays up)"),
    "replay_feedback_fallen": Figure("0/1", 0.0, "full-length replay with the solver's feedback gains falls (needs gains)"),
    "replay_feedback_fall_time": Figure("s", None, "time until the feedback replay falls (None: stays up)"),
    "replay_feedback_base_error": Figure("m", None, "base position error of the feedback replay, largest"),
    "replay_feedback_foot_error": Figure("cm", None, "sole position error of the feedback replay, largest"),
}

# The figures a kinematic record (no torques, no contact forces) is judged on; the others are
# skipped and the validation says so (`opt2skill.data.validate`).
KINEMATIC = ("joint_limit_violation", "velocity_violation", "foot_slip", "foot_penetration", "derived_fields_error")
