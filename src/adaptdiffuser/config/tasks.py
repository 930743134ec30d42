"""Tasks: the unit of the pipeline. ``task.<name>`` in params.yaml holds one task's settings: its ``family``, the
family's own sections (validated by the model the family registers) and optional overrides of the generic
sections (``model``, ``diffusion``, ``pretrain``, ``planner``, ``evaluate``), merged over the top-level ones.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from pydantic import TypeAdapter, ValidationError

from adaptdiffuser.config.errors import ConfigError, config_error, show
from adaptdiffuser.config.family_settings import family_names, is_family, settings_model
from adaptdiffuser.config.merge import deep_merge
from adaptdiffuser.config.sections import (
    DiffusionParams,
    EvaluateParams,
    ModelParams,
    PlannerParams,
    PretrainParams,
)

#: the generic sections a task entry may override, and their models
GENERIC_SECTIONS: dict[str, type] = {
    "model": ModelParams,
    "diffusion": DiffusionParams,
    "pretrain": PretrainParams,
    "planner": PlannerParams,
    "evaluate": EvaluateParams,
}
TASK_NAME = re.compile(r"[a-z0-9][a-z0-9_-]*")
#: the type of a task's family settings (a family's ``TASK_PARAMS``), so ``task.settings`` is typed in its family
SettingsT = TypeVar("SettingsT")


@dataclass(frozen=True)
class TaskParams(Generic[SettingsT]):
    """One task, resolved: its name and family, the family's own settings, and the generic sections with this
    task's overrides merged in. Stages take one of these (``params.resolve(name)``); a family's code types its tasks
    ``TaskParams[<its settings model>]``."""

    name: str
    family: str
    settings: SettingsT
    model: ModelParams
    diffusion: DiffusionParams
    pretrain: PretrainParams
    planner: PlannerParams
    evaluate: EvaluateParams
    #: the entry as written in params.yaml (to resolve it again over other generic sections)
    entry: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)

    def section(self, name: str) -> dict[str, Any]:
        """A generic section, one of the family's sections, or ``settings`` (all of them), as a plain dict."""
        if name == "settings":
            return _plain(self.settings)
        value = getattr(self, name) if name in GENERIC_SECTIONS else getattr(self.settings, name)
        return _plain(value)


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    if hasattr(value, "model_dump"):
        return value.model_dump()
    return value


def build_task(name: str, entry: Any, generic: Mapping[str, Any]) -> TaskParams[Any]:
    """Validate ``task.<name>``: the family's model for its own keys, the generic overrides merged over
    ``generic`` (the validated top-level sections)."""
    where = f"task.{name}"
    if not TASK_NAME.fullmatch(str(name)):
        raise ConfigError(f"{where}: task names are lower-case letters, digits, '_' and '-', like hopper-medium")
    if not isinstance(entry, Mapping):
        raise ConfigError(f"{where}: must be a mapping with a 'family' key, got {show(entry)}")
    family = entry.get("family")
    if not is_family(family):
        raise ConfigError(f"{where}.family: must be one of {family_names()}, got {show(family)}")
    model = settings_model(family)
    own = {key: value for key, value in entry.items() if key not in GENERIC_SECTIONS}
    try:
        settings = TypeAdapter(model).validate_python(own)
    except ValidationError as err:
        raise config_error(err, model, prefix=where) from None
    check_name = getattr(settings, "check_name", None)
    if check_name is not None:
        check_name(str(name))
    sections: dict[str, Any] = {}
    for key, cls in GENERIC_SECTIONS.items():
        override = entry.get(key) or {}
        if not isinstance(override, Mapping):
            raise ConfigError(f"{where}.{key}: must be a mapping of {key} keys to override, got {show(override)}")
        try:
            sections[key] = TypeAdapter(cls).validate_python(deep_merge(_plain(generic[key]), dict(override)))
        except ValidationError as err:
            raise config_error(err, cls, prefix=f"{where}.{key}") from None
    return TaskParams(name=str(name), family=family, settings=settings, **sections, entry=dict(entry))
