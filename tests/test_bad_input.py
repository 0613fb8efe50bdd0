"""Bad robot input gets one clear error naming the problem; the CLI exits 2 without a traceback."""

import subprocess
import sys

import pytest
import yaml

from opt2skill.errors import ConfigError, ModelError
from opt2skill.model import load_robot
from opt2skill.robots import find_robot_config


def test_unknown_robot_names_the_choices():
    with pytest.raises(ConfigError, match=r"unknown robot 'atlas'.*digit"):
        find_robot_config("atlas")


def test_missing_model_file(digit_copy):
    (digit_copy / "digit.xml").unlink()
    with pytest.raises(ConfigError, match="mjcf file 'digit.xml' not found"):
        load_robot(digit_copy / "robot.yaml")


def test_malformed_model_file(digit_copy):
    (digit_copy / "digit.xml").write_text("<mujoco><worldbody><body name='x'>")
    with pytest.raises(ModelError, match="cannot read MJCF"):
        load_robot(digit_copy / "robot.yaml")


def test_config_joint_names_must_match_the_model(digit_copy):
    path = digit_copy / "robot.yaml"
    raw = yaml.safe_load(path.read_text())
    raw["joints"] = {("left_kne" if k == "left_knee" else k): v for k, v in raw["joints"].items()}
    raw["joint_groups"]["left_leg"] = [("left_kne" if j == "left_knee" else j) for j in raw["joint_groups"]["left_leg"]]
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    with pytest.raises(ModelError, match=r"not the model: \['left_kne'\].*not the config: \['left_knee'\]"):
        load_robot(path)


def test_config_joint_order_must_match_the_model(digit_copy):
    path = digit_copy / "robot.yaml"
    raw = yaml.safe_load(path.read_text())
    items = list(raw["joints"].items())
    items[0], items[1] = items[1], items[0]
    raw["joints"] = dict(items)
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    with pytest.raises(ModelError, match="joint order differs"):
        load_robot(path)


def test_config_naming_a_missing_site(digit_copy):
    path = digit_copy / "robot.yaml"
    raw = yaml.safe_load(path.read_text())
    raw["end_effectors"]["left_hand"] = "left_palm"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    with pytest.raises(ModelError, match=r"sites missing from the model: \['left_palm'\]"):
        load_robot(path)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda raw: raw["joints"]["left_knee"].update(kp=-5), r"joints.left_knee.kp must be a positive"),
        (lambda raw: raw.pop("feet"), r"missing keys \['feet'\]"),
        (lambda raw: raw.update(colour="red"), r"unknown keys \['colour'\]"),
        (lambda raw: raw["joints"]["left_knee"].update(kp="stiff"), r"kp must be a number, got 'stiff'"),
    ],
)
def test_malformed_config_values(digit_copy, edit, message):
    path = digit_copy / "robot.yaml"
    raw = yaml.safe_load(path.read_text())
    edit(raw)
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    with pytest.raises(ConfigError, match=message):
        load_robot(path)


def test_config_that_is_not_yaml(digit_copy):
    (digit_copy / "robot.yaml").write_text("joints: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_robot(digit_copy / "robot.yaml")


def test_cli_reports_one_line_and_exit_code_2():
    result = subprocess.run(
        [sys.executable, "-m", "opt2skill", "robot", "check", "--robot", "atlas"],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 2
    assert "unknown robot 'atlas'" in result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    assert len(result.stderr.strip().splitlines()) == 1


def test_a_copied_robot_folder_loads_by_path(digit_copy):
    """Adding a robot is data only: a robot folder elsewhere on disk loads by path."""
    robot = load_robot(digit_copy)
    assert robot.nu == 20 and robot.config.directory == digit_copy.resolve()
