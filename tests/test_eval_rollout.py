"""Evaluation's own code paths: rollout to record to metrics, the choice of held-out references,
the report files, and the terrain sweep's reference rotation and trial judge."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from envs_support import ROBOT, exact_config, recorded_reference
from eval_support import write_dataset

from opt2skill.data.reader import Dataset
from opt2skill.data.record import build_trajectory
from opt2skill.errors import ConfigError, DataError
from opt2skill.eval.metrics import METRICS, tracking_errors
from opt2skill.eval.references import check_metric_fields, dataset_fingerprints, select_references
from opt2skill.eval.report import EvalReport, TrajectoryResult, read_report
from opt2skill.eval.rollout import rollout
from opt2skill.eval.sweep import SweepSettings, judge, rotate_about_z
from opt2skill.geometry import quat_mul
from opt2skill.sim import Flat, Stairs


@pytest.fixture(scope="module")
def recorded():
    return recorded_reference(80)


def _replay(targets: np.ndarray, scale: float):
    """A policy that plays back the actions of recorded PD targets, one row per call."""
    actions = iter((targets - ROBOT.config.default_pose) / scale)
    return lambda obs: np.tile(next(actions), (len(obs), 1))


def test_replaying_the_recorded_actions_tracks_the_reference_to_rounding(recorded):
    """A reference recorded from the simulator, tracked by replaying the actions that made it: the
    rollout-to-record step lines up states, torques and forces frame by frame, so every error is
    at rounding level. A small change to the actions shows up in the errors."""
    reference, targets = recorded
    config = exact_config()
    [exact] = rollout(ROBOT, [reference], _replay(targets, config.actions.scale), config, threads=1)
    assert exact.cause == "time_out" and exact.tracked.num_frames == reference.num_frames
    e = exact.errors()
    assert e.E_joint < 1e-6 and e.E_ee_foot < 1e-4 and e.E_ee_hand < 1e-4 and e.E_vel_x < 1e-4
    assert e.E_torque < 1e-3 and e.E_force < 1e-2 and not e.fell
    bent = targets.copy()
    bent[:, ROBOT.config.joint_names.index("left_knee")] -= 0.05
    [off] = rollout(ROBOT, [reference], _replay(bent, config.actions.scale), config, threads=1)
    assert off.errors().E_joint > 100 * max(e.E_joint, 1e-7) and off.errors().E_torque > 1.0


def test_a_policy_that_loses_the_reference_is_counted_as_fallen(recorded):
    reference, targets = recorded
    config = exact_config()
    collapse = np.zeros_like(targets)
    collapse[:, [ROBOT.config.joint_names.index(j) for j in ("left_knee", "right_knee")]] = -2.5
    [r] = rollout(ROBOT, [reference], _replay(collapse, config.actions.scale), config, threads=1)
    assert r.fell and r.cause != "time_out" and r.tracked.num_frames < reference.num_frames
    assert tracking_errors(r.reference, r.tracked, fell=r.fell).fell


@pytest.fixture(scope="module")
def four(recorded):
    reference, _ = recorded
    return [dataclasses.replace(reference, params={"depth": 0.01 * i}) for i in range(4)]


def test_held_out_references_are_those_the_policy_did_not_train_on(four, tmp_path):
    ds = Dataset.open(write_dataset(tmp_path / "ds", four))
    prints = dataset_fingerprints(ds)
    assert len(set(prints)) == 4
    trained = prints[:2]
    held = select_references(ds, trained, n=20)
    assert held.indices == (2, 3) and held.seen == (False, False) and "held out" in held.note
    assert select_references(ds, trained, n=1, split="training").indices == (0,)
    every = select_references(ds, trained, n=20, split="all")
    assert every.seen == (True, True, False, False) and "2 of 4 used in training" in every.note
    with pytest.raises(DataError, match="no held-out references.*--dataset"):
        select_references(ds, prints, n=5)
    with pytest.raises(DataError, match="cannot tell which references"):
        select_references(ds, None, n=5)
    assert select_references(ds, None, n=5, split="all").seen == (None,) * 4
    with pytest.raises(ConfigError, match="--split must be one of"):
        select_references(ds, trained, n=5, split="test")
    # The same trajectory in another directory is recognised as seen: identity is task + parameters.
    copy = Dataset.open(write_dataset(tmp_path / "copy", four[1:3]))
    assert select_references(copy, trained, n=5, split="all").seen == (True, False)


def test_datasets_without_what_the_metrics_need_are_refused(recorded, tmp_path):
    reference, _ = recorded
    check_metric_fields(Dataset.open(write_dataset(tmp_path / "ok", [reference])), "recorded")
    with pytest.raises(DataError, match="holds 'recorded' trajectories; the policy was trained on 'walk'"):
        check_metric_fields(Dataset.open(tmp_path / "ok"), "walk")
    feet_only = build_trajectory(ROBOT, reference.qpos, reference.qvel, reference.joint_torque, reference.contact_wrench,
                                 reference.contact_active, task="recorded", contact_names=reference.contact_names,
                                 params={}, seed=0, ee_names=("left_foot", "right_foot"))
    with pytest.raises(DataError, match=r"lacks the end effectors \['left_hand', 'right_hand'\]"):
        check_metric_fields(Dataset.open(write_dataset(tmp_path / "feet", [feet_only])))


def test_report_files_round_trip_with_the_papers_row(recorded, tmp_path):
    reference, _ = recorded
    tracked = dataclasses.replace(reference, qpos=reference.qpos + np.r_[np.zeros(7), 0.01 * np.ones(20)])
    errors = [tracking_errors(reference, tracked), tracking_errors(reference, reference, fell=True)]
    assert all(math.isnan(e.pace) for e in errors)  # a squat has no path
    errors = [dataclasses.replace(e, pace=pace, turn=turn, lead=lead)
              for e, pace, turn, lead in zip(errors, (1.4, 0.9), (-0.3, -0.1), (0.12, -0.04))]
    results = [TrajectoryResult(i, {"depth": 0.1}, False, cause, reference.num_frames, reference.num_frames, e)
               for i, (e, cause) in enumerate(zip(errors, ("time_out", "fall")))]
    report = EvalReport("eval", {"name": "mine", "key": {"checkpoint": "x"}}, {"note": "2 references", "dataset": "d",
                        "indices": [0, 1], "fingerprints": ["a", "b"]}, {"seed": 0}, results)
    json_path, md_path = report.write(tmp_path)
    back = read_report(json_path)
    assert back.key() == report.key() and back.success_rate == 0.5
    assert back.summary()["E_joint"].mean == pytest.approx(0.005) and back.summary()["E_pos_x"].n == 0
    text = md_path.read_text()
    assert "| mine | 0.005 ± 0.005 |" in text and "| Opt2Skill (paper, Table III) | 0.03 ± 0.01 | 4.86 ± 4.18 |" in text
    assert "50% (1/2)" in text and all(m.split("_")[0] in text for m in METRICS)
    assert "Episode ends: time_out 1, fall 1." in text
    assert "median 1.15, 0.90 to 1.40 over 2 references" in text and [r.errors.pace for r in back.results] == [1.4, 0.9]
    assert "median -0.200 rad; left in 0, right in 2 of 2 references" in text
    assert [r.errors.turn for r in back.results] == [-0.3, -0.1]
    assert "median +0.040 m/s, -0.040 to +0.120 over 2 references" in text
    assert [r.errors.lead for r in back.results] == [0.12, -0.04]
    # A report written before the signed pace, turn and lead existed still reads, those unknown.
    old = json.loads(json_path.read_text())
    for t in old["trajectories"]:
        del t["pace"], t["turn"], t["lead"]
    (tmp_path / "old.json").write_text(json.dumps(old))
    older = read_report(tmp_path / "old.json")
    assert all(math.isnan(r.errors.pace) and math.isnan(r.errors.turn) and math.isnan(r.errors.lead)
               for r in older.results)
    assert older.turn_summary() is None and "Turn (" not in older.markdown()
    assert older.lead_summary() is None and "Lead (" not in older.markdown()
    (tmp_path / "bad.json").write_text('{"format": "something else"}')
    with pytest.raises(DataError, match="not an opt2skill evaluation report"):
        read_report(tmp_path / "bad.json")


def _walk_like(reference):
    """The recorded squat carried forward at 0.5 m/s and turning at 0.2 rad/s: a record that moves."""
    t = reference.time
    yaw = 0.2 * t
    qpos, qvel = reference.qpos.copy(), reference.qvel.copy()
    qpos[:, 0] += 0.5 * t
    qpos[:, 3:7] = quat_mul(np.stack([np.cos(yaw / 2), 0 * t, 0 * t, np.sin(yaw / 2)], 1), reference.qpos[:, 3:7])
    qvel[:, 0] += 0.5
    qvel[:, 5] += 0.2
    return build_trajectory(ROBOT, qpos, qvel, reference.joint_torque, reference.contact_wrench, reference.contact_active,
                            task="recorded", contact_names=reference.contact_names, params={}, seed=0)


def test_turning_a_reference_turns_every_world_quantity_and_keeps_the_metrics(recorded):
    walk = _walk_like(recorded[0])
    turned = rotate_about_z(walk, 0.4)
    c, s = np.cos(0.4), np.sin(0.4)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    wrench = turned.contact_wrench
    rebuilt = build_trajectory(ROBOT, turned.qpos, turned.qvel, walk.joint_torque, wrench, walk.contact_active,
                               task="recorded", contact_names=walk.contact_names, params={}, seed=0)
    for name in ("ee_pos", "ee_pos_base", "base_lin_vel", "base_ang_vel", "com"):
        np.testing.assert_allclose(getattr(turned, name), getattr(rebuilt, name), atol=1e-9, err_msg=name)
    np.testing.assert_allclose(turned.qpos[0, :3], walk.qpos[0, :3], atol=1e-12)  # turned about its start
    np.testing.assert_allclose(wrench[..., :3], walk.contact_wrench[..., :3] @ rot.T, atol=1e-12)
    drift = walk.qpos + np.r_[0.0, 0.0, 0.0, np.zeros(4), 0.01 * np.ones(20)]
    drift[:, :2] += np.outer(walk.time / walk.time[-1], [0.02, -0.01])  # from the same start (the pivot)
    shifted = build_trajectory(ROBOT, drift, walk.qvel, walk.joint_torque * 1.1, walk.contact_wrench,
                               walk.contact_active, task="recorded", contact_names=walk.contact_names, params={}, seed=0)
    plain, both = tracking_errors(walk, shifted), tracking_errors(turned, rotate_about_z(shifted, 0.4))
    for name in METRICS:
        assert getattr(both, name) == pytest.approx(getattr(plain, name), rel=1e-6, abs=1e-9, nan_ok=True), name


def test_trial_judge_on_hand_made_motions(recorded):
    walk = _walk_like(recorded[0])  # 0.2 m straight-ish path over 0.4 s
    distance = np.linalg.norm(walk.qpos[-1, :2] - walk.qpos[0, :2])

    def stopped_at(fraction):
        q = walk.qpos.copy()
        q[:, :2] = walk.qpos[0, :2] + fraction * (walk.qpos[:, :2] - walk.qpos[0, :2])
        return dataclasses.replace(walk, qpos=q)

    def verdict(tracked, terrain=Flat(), min_height=0.4):
        return judge(walk, tracked, terrain, 0.0, 0.0, min_height=min_height, max_tilt=1.0, tolerance=0.1)

    assert verdict(walk).success and verdict(walk).progress == pytest.approx(distance)
    assert verdict(stopped_at(0.95)).success and not verdict(stopped_at(0.8)).success
    low = walk.qpos.copy()
    low[40:, 2] = 0.3
    fell = verdict(dataclasses.replace(walk, qpos=low))
    assert fell.fell and not fell.success and fell.fall_time == pytest.approx(walk.time[40])
    # Two 0.3 m steps rise under the path: the flat reference's base height over them is a robot
    # sunk into the stairs (0.43 m above the top step), one that climbs keeps its height above them.
    stairs = SweepSettings(start=walk.qpos[0, 0] + 0.05, step_length=0.1).terrain_for(0.3, 1.0, 0.0)
    assert isinstance(stairs, Stairs) and stairs.height(walk.qpos[-1:, :2])[0] == pytest.approx(0.6)
    assert verdict(walk, stairs, min_height=0.6).fell and not verdict(walk, Flat(), min_height=0.6).fell
    climbed = walk.qpos.copy()
    climbed[:, 2] += stairs.height(walk.qpos[:, :2])
    assert verdict(dataclasses.replace(walk, qpos=climbed), stairs, min_height=0.6).success
