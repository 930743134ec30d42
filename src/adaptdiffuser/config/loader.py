"""Loading ``params.yaml``: YAML into :class:`Params`, every problem a one-line :class:`ConfigError`.

A params file writes every key of the generic sections (:func:`missing_keys`): the defaults live in the config
classes and the profiles overlay them, and ``adaptdiffuser profile`` writes the result with every value resolved
(:func:`adaptdiffuser.config.profiles.apply_profile`, which says why the classes hold the defaults). A task entry may
leave family keys to its family's defaults; ``adaptdiffuser check`` names each one it takes
(:func:`adaptdiffuser.config.defaults.unwritten`)."""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml
from pydantic import TypeAdapter, ValidationError

from adaptdiffuser.config.errors import ConfigError, config_error
from adaptdiffuser.config.params import Params
from adaptdiffuser.config.sweep_settings import check_space

__all__ = ["ConfigError", "load_params", "params_from_dict"]

_PARAMS = TypeAdapter(Params)
#: top-level keys a params file may leave out: they have a meaning when absent (no imports; collect every task that
#: is not imported; no pretrained models; pretrain every task that has none; no sweep: a sweep trial's params have
#: none). Every other key of the generic sections must be
#: written: a run uses only what the file says.
OPTIONAL_KEYS = ("imports", "collect_tasks", "pretrained", "pretrain_tasks", "sweep")
#: keys whose entries are not sections with fixed keys (task entries are checked by their family's model)
OPEN_KEYS = ("task", "phases", "sweep.space")


def missing_keys(raw: Mapping[str, Any], cls: type = Params, prefix: str = "") -> list[str]:
    """The keys of the generic sections (``Params`` and its nested sections) that ``raw`` does not write."""
    hints = typing.get_type_hints(cls)
    missing: list[str] = []
    for field in dataclasses.fields(cls):
        key = f"{prefix}{field.name}"
        if key in OPTIONAL_KEYS:
            continue
        if field.name not in raw:
            missing.append(key)
            continue
        value, kind = raw[field.name], hints[field.name]
        if key not in OPEN_KEYS and dataclasses.is_dataclass(kind) and isinstance(value, Mapping):
            missing += missing_keys(value, kind, f"{key}.")
    return missing


def read_yaml_mapping(path: Path, not_a_mapping: str) -> dict:
    """The mapping a YAML file holds (an empty file: none); bad YAML, or ``not_a_mapping`` when it holds something
    else, is refused in one line naming the file."""
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        where = getattr(err, "problem_mark", None)
        line = f" (line {where.line + 1})" if where is not None else ""
        raise ConfigError(f"{path}: not valid YAML{line}: {getattr(err, 'problem', None) or err}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: {not_a_mapping}")
    return raw


def load_params(path: str | Path = "params.yaml", set_by_caller: tuple[str, ...] = ()) -> Params:
    """Load and validate ``params.yaml``; raise :class:`ConfigError` naming the first bad key, or the keys of the
    generic sections it leaves out (:func:`missing_keys`) other than those under a prefix in ``set_by_caller``
    (which take their defaults: the caller overrides them, as kept-model evaluation does ``evaluate.``)."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"params file not found: {path}")
    raw = read_yaml_mapping(path, "top level must be a mapping of sections")
    params = params_from_dict(raw)  # a bad value is named first
    missing = [key for key in missing_keys(raw) if not key.startswith(set_by_caller)]
    if missing:
        shown = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
        raise ConfigError(
            f"{path}: missing {shown}; a run uses only the values its params file writes: start from a profile "
            "(adaptdiffuser profile quick) and change what you need"
        )
    return params


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
