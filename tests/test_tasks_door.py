"""Door pushing while walking: the door prop (MuJoCo hinge with spring and damper, the record's
door pose), the task's plan (reach, then the walk's phases turning about the hinge with both hands
on the panel), a real solved record whose hand forces hold the door's hinge torque and whose door
the optimizer's feedback expert opens in MuJoCo as the reference does, bad inputs; and downstream:
the batched simulator's door slots, the expert opening the door in the tracking environment, a
door dataset training and evaluating briefly with the door's metric."""

from pathlib import Path

import mujoco
import numpy as np
import pytest

from opt2skill.data.trajfile import read_trajectory, write_trajectory
from opt2skill.data.validate import validate
from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.scene import Door, Scene, build_model, prop_hinge
from opt2skill.tasks import get_task, task_info
from opt2skill.tasks.door import HANDS, door_metrics, expert_hinge_angles, hinge_torques, torque_imbalance

# A real solve, with the solver's gains: tests/data/door_push/README.md says how it was made.
RECORD = Path(__file__).parent / "data" / "door_push" / "seed0_short" / "trajectories" / "000000.h5"


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


@pytest.fixture(scope="module")
def record():
    return read_trajectory(RECORD)


def test_a_door_round_trips_through_the_scene_and_the_record(robot, record, tmp_path):
    door = Door(hinge=(0.6, 0.5), mass=12.0, stiffness=5.0, damping=1.5, name="front_door")
    scene = Scene(props=(door,))
    assert Scene.from_dict(scene.to_dict()) == scene
    assert scene.to_dict()["props"][0]["kind"] == "door"
    # the record's door pose (the hinge frame turned by the planned angle) survives the file
    write_trajectory(tmp_path / "000000.h5", record, 0)
    again = read_trajectory(tmp_path / "000000.h5")
    assert again.scene == record.scene
    np.testing.assert_array_equal(again.prop_poses["door"], record.prop_poses["door"])
    angle = record.scene.prop("door").angle_of(record.prop_poses["door"])
    assert angle[0] == pytest.approx(0.0, abs=1e-12) and angle[-1] == pytest.approx(record.params["angle"], abs=1e-6)


def test_mujoco_builds_the_door_on_a_hinge_whose_spring_closes_it(robot):
    door = Door(hinge=(5.0, 0.45), mass=6.0, stiffness=4.0, damping=2.0, max_angle=1.5)  # far from the robot
    model = build_model(robot, Scene(props=(door,)))
    joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "door/hinge")
    assert model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_HINGE and model.nq == robot.nq + 1
    assert model.jnt_stiffness[joint] == 4.0 and model.dof_damping[model.jnt_dofadr[joint]] == 2.0
    np.testing.assert_allclose(model.jnt_range[joint], [0.0, 1.5])
    # its inertia about the hinge is the one the task's torque balance uses
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "door")
    data = mujoco.MjData(model)
    at = prop_hinge(model, "door")
    data.qpos[at] = 1.0
    mujoco.mj_forward(model, data)
    dof = model.jnt_dofadr[joint]
    assert model.dof_M0[dof] == pytest.approx(door.hinge_inertia, rel=1e-9)
    assert data.qfrc_spring[dof] == pytest.approx(-4.0) and model.body_mass[body] == 6.0
    for _ in range(2000):  # 2 s: the spring and damper close it against its stop
        mujoco.mj_step(model, data)
    assert data.qpos[at] < 0.05
    # the panel's face where a hand presses, and its normal towards the robot, follow the angle
    point = door.panel_point(np.pi / 2, 0.5, 1.0)
    np.testing.assert_allclose(point, [5.0 + 0.5, 0.45 - door.thickness / 2, 1.0], atol=1e-12)  # opened a quarter turn
    np.testing.assert_allclose(door.face_normal(0.0), [-1.0, 0.0, 0.0], atol=1e-12)


def test_the_plan_reaches_to_the_panel_then_walks_about_the_hinge_with_both_hands_on_it(robot):
    task = get_task("door_push", robot)
    params = task.param_space().sample(0, 0)
    plan = task.plan(params)
    labels = [p.label for p in plan.phases]
    assert labels[:4] == ["stand", "reach", "onto the door", "stand"]
    walk = plan.phases[3:]
    assert sum(p.label.startswith("swing") for p in walk) == int(round(params["steps"]))
    assert all({"left_hand", "right_hand"} <= {c.name for c in p.contacts} for p in walk)
    assert not any(c.name in HANDS for p in plan.phases[:3] for c in p.contacts)
    # the walk turns about the hinge: the CoM stays at one distance from it, the heading is the door's angle
    gait, door = plan.context, plan.scene.prop("door")
    radius = np.linalg.norm(gait.com_xy - np.array(door.hinge), axis=1)
    assert np.ptp(radius) < 2e-3 and gait.heading[-1] == pytest.approx(params["angle"], abs=1e-9)
    # each hand's path is the arc its point of the panel describes
    for h in HANDS:
        start = next(c for c in walk[0].contacts if c.name == h).path
        p, v, _ = start(gait.duration / 2)
        assert np.linalg.norm(p[:2] - door.hinge) == pytest.approx(np.linalg.norm(task.hand_on_panel(door, h, 0.0)[:2] - door.hinge))
        assert abs(v @ (p - [*door.hinge, p[2]])) < 1e-9


def test_the_solved_record_is_accepted_and_its_hand_forces_hold_the_doors_hinge_torque(robot, record):
    task = get_task("door_push", robot)
    door = record.scene.prop("door")
    applied, needed = hinge_torques(record, door)
    assert needed.max() > 1.0  # the door resists: spring, damper and inertia
    imbalance = torque_imbalance(record, door)
    assert np.sqrt(np.mean(imbalance**2)) < 1.0 and np.abs(imbalance).max() < 4.0
    errors = task.task_errors(record)
    result = validate(robot, record, task_errors=errors)
    assert result["accepted"], result["reasons"]
    assert errors["hand_friction"]["value"] <= 1.0 and errors["body_contacts"]["value"] == 0


def test_the_hinge_angle_in_the_experts_replay_follows_the_reference(robot, record):
    """The optimizer's feedback expert in MuJoCo with the real door (spring, damper, inertia; the
    hands press on it by contact alone) opens it along the reference's angle."""
    door = record.scene.prop("door")
    reference = door.angle_of(record.prop_poses["door"])
    replayed = expert_hinge_angles(robot, record, "door")
    assert len(replayed) == record.num_frames  # the expert stayed up to the end
    assert np.abs(replayed - reference).max() < 0.1
    assert replayed[-1] == pytest.approx(reference[-1], abs=0.05) and reference[-1] > 0.3
    # the task metric: the tracked door's angle against the reference's
    tracked = read_trajectory(RECORD)
    tracked.prop_poses = {"door": door.pose(replayed)}
    metrics = door_metrics(record, tracked)
    assert metrics["door_final_error"][0] == pytest.approx(np.degrees(abs(replayed[-1] - reference[-1])))
    assert task_info("door_push").metrics is door_metrics


def test_bad_door_inputs_get_one_clear_error(robot):
    with pytest.raises(ConfigError, match=r"door 'door': stiffness must be in \[0, 200\] N m/rad, got -1"):
        Door(stiffness=-1.0)
    with pytest.raises(ConfigError, match=r"unknown prop kind 'gate'; kinds: box, shelf, desk, door"):
        Scene.from_dict({"props": [{"kind": "gate"}]})
    with pytest.raises(ConfigError, match=r"scene prop 'door': unknown fields \['spring'\]; fields: hinge, yaw"):
        Scene.from_dict({"props": [{"kind": "door", "spring": 3.0}]})
    task = get_task("door_push", robot)
    params = task.param_space().sample(0, 0)
    with pytest.raises(ConfigError, match=r"'door_mass' = 50 kg is outside its allowed range \[1, 40\]"):
        task.solve({**params, "door_mass": 50.0}, seed=0)
    with pytest.raises(ConfigError, match=r"angle = 1.3 rad in 4 steps of 0.4 s needs a turn of .* rad/s"):
        task.plan({**params, "angle": 1.3, "steps": 4, "step_duration": 0.4})
    with pytest.raises(ConfigError, match=r"door_mass = 40 kg .* swings on ahead of the hands"):
        task.plan({**params, "door_mass": 40.0, "stiffness": 0.0, "damping": 0.0})
    with pytest.raises(ConfigError, match=r"sampling ranges reach a door that cannot be pushed"):
        get_task("door_push", robot, {"ranges": {"door_mass": [4.0, 40.0], "stiffness": [0.0, 5.0], "damping": [0.0, 1.0]}})


def test_the_batched_simulator_gives_each_world_its_door_and_reports_its_angle(robot, record):
    """Door slots: each world's door at its hinge with its own spring, damper, mass and inertia (or
    none), reset to a given angle, its pose (the hinge frame) among the moving props' outputs."""
    from opt2skill.scene import Box
    from opt2skill.sim.mujoco_sim import MujocoBatchedSim

    door = record.scene.prop("door")
    sim = MujocoBatchedSim(robot, 3, prop_sets=[record.scene.props, (Box(pos=(0.5, 1.0, 0.15)),), ()])
    assert (sim.props.nfree, sim.props.nhinged, sim.props.nmoving) == (1, 1, 2)
    params = sim.params
    params.props[:] = [0, 1, 2]
    frame = 700
    pose = np.tile(sim.props.rest_poses(1), (3, 1, 1))
    pose[0] = sim.props.rest_poses(0)
    pose[0, 1] = record.prop_poses["door"][frame]
    out = sim.reset(np.arange(3), np.tile(record.qpos[frame], (3, 1)), np.tile(record.qvel[frame], (3, 1)),
                    params=params, prop_pose=pose)
    assert door.angle_of(out.prop_pose[0, 1]) == pytest.approx(door.angle_of(record.prop_poses["door"][frame]))
    np.testing.assert_allclose(out.prop_pose[1, 0], sim.props.rest_poses(1)[0], atol=1e-9)  # world 1's box
    joint = mujoco.mj_name2id(sim.models[0], mujoco.mjtObj.mjOBJ_JOINT, "props_hinged_0/hinge")
    dof = sim.models[0].jnt_dofadr[joint]
    assert sim.models[0].jnt_stiffness[joint] == door.stiffness and sim.models[0].dof_damping[dof] == door.damping
    assert sim.models[0].dof_M0[dof] == pytest.approx(door.hinge_inertia, rel=1e-9)
    assert sim.models[1].jnt_stiffness[joint] == 0.0  # worlds without a door have a hidden, inert slot
    out = sim.step(np.tile(record.qpos[frame, 7:], (3, 1)))
    assert out.prop_vel[0, 1, 5] != 0.0 and np.all(out.prop_pose[1:, 1, 3] == 1.0)


def test_the_expert_opens_the_door_in_the_tracking_environment(robot, tmp_path):
    """The environment rebuilds the door in its world; the optimizer's feedback expert, at the
    policy's rate in its action space, tracks the reference to the end and opens the door with it."""
    from opt2skill.expert.play import play_expert

    dataset = _copy(tmp_path)
    result = play_expert(dataset, n=1)
    (motion,) = result.motions
    assert motion.cause == "time_out"
    reference = read_trajectory(RECORD)
    metrics = door_metrics(reference, motion.record(robot, reference))
    assert metrics["door_angle_error"][0] < 3.0  # degrees


def test_a_door_dataset_trains_and_evaluates_briefly_with_the_door_metric(tmp_path):
    from opt2skill.eval.evaluate import EvalRequest, evaluate
    from opt2skill.rl import session
    from opt2skill.rl.session import TrainRequest

    dataset, run = _copy(tmp_path), tmp_path / "run"
    session.train(TrainRequest(dataset=dataset, out=run, steps=192, num_envs=2), progress=False)
    report, _ = evaluate(EvalRequest(run, dataset=dataset, n=1, split="training"), progress=False)
    assert {"door_angle_error", "door_final_error"} <= set(report.task_summary())
    assert not any(name.startswith("door_placed") for name in report.task_summary())  # a box's metric, not a door's


def _copy(tmp_path: Path) -> Path:
    """The committed door dataset, copied (training writes its frame cache beside the data)."""
    import shutil

    out = tmp_path / "door_push"
    shutil.copytree(RECORD.parent.parent, out)
    return out


def test_videos_show_the_door_where_the_record_has_it(robot, record):
    from opt2skill.eval.render import _prop_placer, scene_model

    model = scene_model(robot, ghost=False, scene=record.scene)
    data = mujoco.MjData(model)
    place = _prop_placer(model, record.scene, record.prop_poses)
    place(data, 700)
    door = record.scene.prop("door")
    assert data.qpos[prop_hinge(model, "door")] == pytest.approx(door.angle_of(record.prop_poses["door"][700]))
