"""The defaults of every params key, as the config classes state them (the one place a default is written), in the
form ``params.yaml`` writes them.

The profiles are overlays over these defaults (:mod:`adaptdiffuser.config.profiles`); :func:`complete` writes every
default a profile leaves out into the params file, so ``params.yaml`` holds every value a run uses (DVC tracks each
key a stage depends on) and :func:`unwritten` names the family keys a hand-written task entry leaves to its
family's defaults (``adaptdiffuser check`` prints them).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel

from adaptdiffuser.config.family_settings import is_family, settings_model
from adaptdiffuser.config.loader import params_from_dict
from adaptdiffuser.config.merge import deep_merge
from adaptdiffuser.config.params import Params

#: the order of the top-level keys in a written params file: what runs first, then the sections
KEY_ORDER = (
    "tasks",
    "unseen_tasks",
    "collect_tasks",
    "imports",
    "pretrain_tasks",
    "pretrained",
    "evolve",
    "task",
    "model",
    "diffusion",
    "pretrain",
    "planner",
    "evaluate",
    "alpha",
    "compile",
    "seeds",
    "evolution",
    "phases",
    "sweep",
)


def plain(value: Any) -> Any:
    """A config value as YAML writes it: dataclasses and pydantic models as mappings, tuples as lists."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, BaseModel):
        return {name: plain(getattr(value, name)) for name in type(value).model_fields}
    if isinstance(value, Mapping):
        return {str(key): plain(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [plain(item) for item in value]
    return value


def class_defaults() -> dict[str, Any]:
    """Every top-level key's default (``Params()``), the default task's entry as its family key alone;
    ``collect_tasks`` and ``pretrain_tasks`` are left out (absent, they are computed from ``tasks`` and ``imports``
    or ``pretrained``), ``phases`` and ``sweep.space`` are written as the (empty) mappings a params file gives
    them."""
    defaults = Params()
    values: dict[str, Any] = {}
    for key in KEY_ORDER:
        if key == "task":
            values[key] = {name: {"family": task.family} for name, task in defaults.task.items()}
        elif key == "phases":
            values[key] = {}
        elif key not in ("collect_tasks", "pretrain_tasks"):
            values[key] = plain(getattr(defaults, key))
    values["sweep"]["space"] = {}
    return values


def family_defaults(family: str) -> dict[str, Any]:
    """Every key of a task entry of ``family`` at its default, ``family`` first."""
    return {"family": family} | plain(settings_model(family)())


def complete(raw: Mapping[str, Any]) -> dict[str, Any]:
    """``raw`` (a profile merged over its parts) with every default it leaves out written in: the generic sections'
    keys from :func:`class_defaults`, each task entry's family keys from :func:`family_defaults` (a task's
    overrides of the generic sections stay as written: they are merged over the top-level sections when loaded)."""
    full = deep_merge(class_defaults(), dict(raw))
    tasks = full.get("task")
    if isinstance(tasks, Mapping):
        full["task"] = {name: _complete_entry(entry) for name, entry in tasks.items()}
    if "collect_tasks" not in full:  # written, as dvc.yaml's collect stage iterates over it
        full["collect_tasks"] = list(params_from_dict(full).collect_tasks or ())
    if "pretrain_tasks" not in full:  # written, as dvc.yaml's pretrain stage iterates over it
        full["pretrain_tasks"] = list(params_from_dict(full).pretrain_tasks or ())
    return {key: full[key] for key in KEY_ORDER if key in full} | full


def _complete_entry(entry: Any) -> Any:
    if not isinstance(entry, Mapping) or not is_family(entry.get("family")):
        return entry  # not a task entry: validation names the problem
    return deep_merge(family_defaults(entry["family"]), dict(entry))


def unwritten(raw: Mapping[str, Any]) -> list[str]:
    """The family keys the task entries of ``raw`` (a params file) leave out, each as ``task.<name>.<key>=<the
    default it takes>``."""
    missing: list[str] = []
    for name, entry in (raw.get("task") or {}).items():
        if isinstance(entry, Mapping) and is_family(entry.get("family")):
            missing += _left_out(entry, family_defaults(entry["family"]), f"task.{name}.")
    return missing


def _left_out(written: Mapping[str, Any], defaults: Mapping[str, Any], prefix: str) -> list[str]:
    out: list[str] = []
    for key, default in defaults.items():
        if key not in written:
            out += [f"{prefix}{k}={v!r}" for k, v in _leaves(default, key).items()]
        elif isinstance(default, Mapping) and default and isinstance(written[key], Mapping):
            out += _left_out(written[key], default, f"{prefix}{key}.")
    return out


def _leaves(value: Any, key: str) -> dict[str, Any]:
    if isinstance(value, Mapping) and value:
        return {k: v for child, item in value.items() for k, v in _leaves(item, f"{key}.{child}").items()}
    return {key: value}
