"""Task lookup, config overrides and parameters: every bad input is a clear ConfigError."""

import dataclasses

import pytest

from opt2skill.errors import ConfigError
from opt2skill.model import load_robot
from opt2skill.trajopt.config import load_overrides
from opt2skill.tasks import available_tasks, get_task

WALK = dict(speed=0.5, clearance=0.15, step_duration=0.35, double_support=0.2, lateral_speed=0.0,
            yaw_rate=0.0, height_offset=0.0)


@pytest.fixture(scope="module")
def robot():
    return load_robot("digit")


def test_registry_lists_tasks_and_names_them_on_error(robot):
    assert {"squat", "stairs", "walk"} <= set(available_tasks())
    with pytest.raises(ConfigError, match=r"unknown task 'run'; tasks: .*squat.*walk"):
        get_task("run", robot)


def test_overrides_nested_or_dotted_leave_the_defaults_alone(robot):
    task = get_task("walk", robot, {"solver.dt": 0.04, "weights": {"swing": 10.0}, "steps": 3})
    assert task.config.solver.dt == 0.04 and task.config.weights.swing == 10.0 and task.config.steps == 3
    default = get_task("walk", robot)
    assert default.config.solver.dt != 0.04 and default.config.steps == 0
    assert dataclasses.replace(default.config) == default.config


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"solver.dtt": 0.1}, r"unknown config key 'solver.dtt'; keys here: dt, integrator"),
        ({"stepz": 3}, r"unknown config key 'stepz'"),
        ({"steps": 2.5}, r"'steps' must be an integer"),
        ({"solver.keep_gains": "yes"}, r"'solver.keep_gains' must be true or false"),
        ({"solver.dt": 0.033}, r"solver.dt = 0.033 s must be a positive multiple of the frame period"),
        ({"solver.completion": "magic"}, r"solver.completion must be one of"),
        ({"solver.reg_increase_below": 0.5}, r"solver.reg_increase_below must be in \(0, 0.5\)"),
        ({"solver.accept_step": 1.0}, r"solver.accept_step must be in \[0, 1\)"),
        ({"solver": 3}, r"'solver' is a section"),
        ({"ranges": {"speed": [0.0, 2.0]}}, r"'speed' = 2 m/s is outside its allowed range \[0, 1.5\] m/s"),
        ({"ranges": {"sped": [0.0, 1.0]}}, r"unknown parameter 'sped'"),
    ],
)
def test_bad_overrides_name_the_key_and_what_is_allowed(robot, overrides, message):
    with pytest.raises(ConfigError, match=message):
        get_task("walk", robot, overrides)


def test_bad_parameters_name_the_parameter_and_its_range(robot):
    task = get_task("walk", robot)
    with pytest.raises(ConfigError, match=r"'clearance' = 0.5 m is outside its allowed range \[0.03, 0.3\] m"):
        task.solve({**WALK, "clearance": 0.5}, seed=0)
    with pytest.raises(ConfigError, match=r"missing parameters \['height_offset'\]"):
        task.solve({k: v for k, v in WALK.items() if k != "height_offset"}, seed=0)
    with pytest.raises(ConfigError, match=r"'depth' = -0.1 m is outside"):
        get_task("squat", robot).solve({"depth": -0.1}, seed=0)


def test_sampling_ranges_are_configurable_and_seeded(robot):
    task = get_task("walk", robot, {"ranges": {"speed": [0.2, 0.4]}})
    samples = [task.param_space().sample(5, i) for i in range(20)]
    assert all(0.2 <= s["speed"] <= 0.4 for s in samples)
    assert all(s["lateral_speed"] == 0.0 and s["yaw_rate"] == 0.0 for s in samples)  # the paper's dataset
    assert samples[3] == get_task("walk", robot, {"ranges": {"speed": [0.2, 0.4]}}).param_space().sample(5, 3)


def test_overrides_load_from_yaml(tmp_path, robot):
    path = tmp_path / "walk.yaml"
    path.write_text("solver:\n  dt: 0.04\nweights.swing: 2000.0\n")
    task = get_task("walk", robot, load_overrides(path))
    assert task.config.solver.dt == 0.04 and task.config.weights.swing == 2000.0
    (tmp_path / "bad.yaml").write_text("solver: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_overrides(tmp_path / "bad.yaml")
    with pytest.raises(ConfigError, match="not found"):
        load_overrides(tmp_path / "missing.yaml")


def test_command_line_values_take_the_type_they_read_as():
    from opt2skill.trajopt.config import parse_value

    assert parse_value("3") == 3 and isinstance(parse_value("3"), int)
    assert parse_value("0.2") == 0.2 and parse_value("1e-3") == 0.001  # YAML would read 1e-3 as text
    assert parse_value("TRUE") is True and parse_value("false") is False
    assert parse_value("euler") == "euler"
