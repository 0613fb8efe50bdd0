"""Reading YAML configuration files with one clear error for each way they can be wrong."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from opt2skill.errors import ConfigError


def read_mapping(path: str | Path, kind: str, empty_ok: bool = False) -> dict[str, Any]:
    """The mapping stored in a YAML file; `kind` names the file in errors ("robot config", ...)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{kind} not found: {path}")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{kind} {path} is not valid YAML: {str(exc).splitlines()[0]}") from None
    if raw is None and empty_ok:
        return {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{kind} {path} must be a mapping of keys to values")
    return raw
