"""Task configs: one frozen dataclass of defaults per task, changed only by checked overrides.

Overrides come as a mapping, nested (`{"solver": {"max_iter": 50}}`) or dotted
(`{"solver.max_iter": 50}`), or from a YAML file with the same structure. Unknown keys and values
of the wrong type are `ConfigError`s naming the key and what is allowed; value checks belong to
each config's `check()`. A task never copies its config to vary it: it applies overrides.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping, TypeVar

from opt2skill.errors import ConfigError
from opt2skill.yaml_files import read_mapping

C = TypeVar("C")


def apply_overrides(config: C, overrides: Mapping[str, Any] | None, *, where: str = "") -> C:
    """A copy of `config` with `overrides` applied and checked (the original is unchanged)."""
    nested = _nest(overrides or {}, where)
    updated = _apply(config, nested, where)
    check = getattr(updated, "check", None)
    if check is not None:
        check()
    return updated


def load_overrides(path: str | Path) -> dict[str, Any]:
    """Overrides from a YAML file (a mapping with the config's keys)."""
    return read_mapping(path, "task config", empty_ok=True)


def config_to_dict(config: Any) -> dict[str, Any]:
    """Plain (JSON-able) values of a config, for provenance."""
    return dataclasses.asdict(config)


def _nest(overrides: Mapping[str, Any], where: str) -> dict[str, Any]:
    nested: dict[str, Any] = {}
    for key, value in overrides.items():
        if not isinstance(key, str) or not key:
            raise ConfigError(f"{where}override keys must be non-empty strings, got {key!r}")
        head, _, rest = key.partition(".")
        if rest:
            value = {rest: value}
        if isinstance(value, Mapping) and isinstance(nested.get(head), dict):
            nested[head].update(_nest(value, where))
        elif isinstance(value, Mapping):
            nested[head] = _nest(value, where)
        else:
            nested[head] = value
    return nested


def _apply(config: Any, overrides: dict[str, Any], where: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(config)}
    changes = {}
    for key, value in overrides.items():
        path = f"{where}{key}"
        if key not in fields:
            raise ConfigError(f"unknown config key '{path}'; keys here: {', '.join(fields)}")
        current = getattr(config, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, Mapping):
                raise ConfigError(f"config key '{path}' is a section; give a mapping of its keys")
            changes[key] = _apply(current, dict(value), f"{path}.")
        else:
            changes[key] = _coerce(current, value, path)
    return dataclasses.replace(config, **changes)


def _coerce(current: Any, value: Any, path: str) -> Any:
    """`value` converted to the type of the default `current`, or a ConfigError."""
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"config key '{path}' must be true or false, got {value!r}")
        return value
    if isinstance(current, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config key '{path}' must be an integer, got {value!r}")
        return value
    if isinstance(current, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config key '{path}' must be a number, got {value!r}")
        return float(value)
    if isinstance(current, str):
        if not isinstance(value, str):
            raise ConfigError(f"config key '{path}' must be a string, got {value!r}")
        return value
    if isinstance(current, tuple):
        if isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
            raise ConfigError(f"config key '{path}' must be a list of {len(current)} values, got {value!r}")
        if current and len(value) != len(current):
            raise ConfigError(f"config key '{path}' must have {len(current)} values, got {len(value)}")
        return tuple(_coerce(c, v, f"{path}[{i}]") for i, (c, v) in enumerate(zip(current, value)))
    if isinstance(current, dict):
        if not isinstance(value, Mapping):
            raise ConfigError(f"config key '{path}' must be a mapping, got {value!r}")
        return {**current, **value}
    raise ConfigError(f"config key '{path}' cannot be overridden")


def parse_value(text: str) -> bool | int | float | str:
    """An override's value given as text (a command line): true/false, an integer, a number, or
    the text itself; the config's types and checks then judge it."""
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def require(condition: bool, message: str) -> None:
    """For `check()` methods: raise ConfigError(message) unless `condition`."""
    if not condition:
        raise ConfigError(message)
