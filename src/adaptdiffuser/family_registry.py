"""The one place families are registered: ``family name -> package``, imported only when asked for, so the core
never imports a family's simulator (or its heavy dependencies) unless a task of that family runs.

A family package has ``params.py`` defining ``TASK_PARAMS`` (the model of its ``task.<name>`` entries, light to
import) and ``family.py`` defining ``FAMILY`` (its :class:`~adaptdiffuser.contract.Family` subclass).
Adding a family = that folder plus one line here.

The registry sits above config and the contract: importing it hands config each family's settings model
(:func:`adaptdiffuser.config.family_settings.register_family`); the package's ``__init__`` imports it, so this is
done before any params are read. Config never imports the registry.
"""

from __future__ import annotations

import importlib
from functools import cache, partial
from typing import TYPE_CHECKING, Any

from adaptdiffuser.config.family_settings import register_family

if TYPE_CHECKING:
    from adaptdiffuser.contract import Family

FAMILIES: dict[str, str] = {
    "maze2d": "adaptdiffuser.families.maze2d",
    "locomotion": "adaptdiffuser.families.locomotion",
    "kuka": "adaptdiffuser.families.kuka",
}


def _package(name: str) -> str:
    if name not in FAMILIES:
        raise KeyError(f"unknown family {name!r}; registered families: {sorted(FAMILIES)}")
    return FAMILIES[name]


def task_params_model(name: str) -> type:
    """The model of the family's task entries (its ``params.TASK_PARAMS``)."""
    return importlib.import_module(f"{_package(name)}.params").TASK_PARAMS


for _name in FAMILIES:  # config validates task entries with these models, loaded when a task of the family is read
    register_family(_name, partial(task_params_model, _name))


@cache
def get_family(name: str) -> Family[Any]:
    """The family registered as ``name``; ``KeyError`` naming the known families otherwise."""
    family = importlib.import_module(f"{_package(name)}.family").FAMILY()
    if family.name != name:
        raise TypeError(f"{FAMILIES[name]} declares family {family.name!r}, registered as {name!r}")
    return family
