"""Task parameters: seeded sampling inside configured ranges, and clear errors outside allowed ranges."""

import pytest

from opt2skill.errors import ConfigError
from opt2skill.trajopt.params import Param, ParamSpace

SPEED = Param("speed", allowed=(0.0, 1.5), default_range=(0.0, 1.5), unit="m/s", help="forward speed")
YAW = Param("yaw_rate", allowed=(-0.5, 0.5), default_range=(0.0, 0.0), unit="rad/s", help="turning rate")


def test_same_seed_and_index_give_the_same_parameters():
    space = ParamSpace([SPEED, YAW])
    assert space.sample(7, 3) == ParamSpace([SPEED, YAW]).sample(7, 3)
    assert space.sample(7, 3) != space.sample(7, 4)
    assert space.sample(7, 3) != space.sample(8, 3)


def test_samples_stay_in_their_ranges_and_fixed_ranges_are_fixed():
    space = ParamSpace([SPEED, YAW], ranges={"speed": (0.5, 1.0)})
    values = [space.sample(0, i) for i in range(200)]
    assert all(0.5 <= v["speed"] <= 1.0 for v in values)
    assert all(v["yaw_rate"] == 0.0 for v in values)
    assert max(v["speed"] for v in values) - min(v["speed"] for v in values) > 0.4


def test_out_of_range_value_names_parameter_and_range():
    space = ParamSpace([SPEED, YAW])
    with pytest.raises(ConfigError, match=r"'speed' = 2 m/s is outside its allowed range \[0, 1.5\] m/s"):
        space.check({"speed": 2.0, "yaw_rate": 0.0})
    with pytest.raises(ConfigError, match=r"'speed' = 1.8 m/s is outside"):
        ParamSpace([SPEED], ranges={"speed": (0.0, 1.8)})
    with pytest.raises(ConfigError, match="unknown parameter 'spede'"):
        ParamSpace([SPEED], ranges={"spede": (0.0, 1.0)})
    with pytest.raises(ConfigError, match="empty"):
        ParamSpace([SPEED], ranges={"speed": (1.0, 0.5)})
    with pytest.raises(ConfigError, match=r"missing parameters \['yaw_rate'\]"):
        space.check({"speed": 1.0})
