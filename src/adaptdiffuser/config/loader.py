"""Loading ``params.yaml``: YAML into :class:`Params`, every problem a one-line :class:`ConfigError`."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml
from pydantic import TypeAdapter, ValidationError

from adaptdiffuser.config.errors import ConfigError, config_error
from adaptdiffuser.config.params import Params
from adaptdiffuser.config.sweep import check_space

__all__ = ["ConfigError", "load_params", "params_from_dict"]

_PARAMS = TypeAdapter(Params)


def load_params(path: str | Path = "params.yaml") -> Params:
    """Load and validate ``params.yaml``; raise :class:`ConfigError` naming the first bad key."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"params file not found: {path}")
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        where = getattr(err, "problem_mark", None)
        line = f" (line {where.line + 1})" if where is not None else ""
        raise ConfigError(f"{path}: not valid YAML{line}: {getattr(err, 'problem', None) or err}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: top level must be a mapping of sections")
    return params_from_dict(raw)


def params_from_dict(raw: Mapping[str, Any]) -> Params:
    """Build and validate params from the parsed YAML mapping (which is left unchanged)."""
    if not isinstance(raw, Mapping):
        raise ConfigError(f"params: top level must be a mapping of sections, got {type(raw).__name__}")
    try:
        params = _PARAMS.validate_python(dict(raw))
    except ValidationError as err:
        raise config_error(err, Params) from None
    check_space(dict(raw), params.sweep, params_from_dict)
    return params
