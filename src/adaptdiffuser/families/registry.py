"""The one place families are registered: ``family name -> "module:Class"``, imported only when asked for, so
the core never imports a family's simulator (or its heavy dependencies) unless a task of that family runs.

Adding a family = a folder under ``families/`` with a :class:`~adaptdiffuser.families.base.Family` subclass,
plus one line here.
"""

from __future__ import annotations

import importlib
from functools import cache

from adaptdiffuser.families.base import Family

FAMILIES: dict[str, str] = {
    "locomotion": "adaptdiffuser.families.locomotion.family:LocomotionFamily",
}


@cache
def get_family(name: str) -> Family:
    """The family registered as ``name``; ``KeyError`` naming the known families otherwise."""
    if name not in FAMILIES:
        raise KeyError(f"unknown family {name!r}; registered families: {sorted(FAMILIES)}")
    module_name, class_name = FAMILIES[name].split(":")
    family = getattr(importlib.import_module(module_name), class_name)()
    if family.name != name:
        raise TypeError(f"{FAMILIES[name]} declares family {family.name!r}, registered as {name!r}")
    return family
