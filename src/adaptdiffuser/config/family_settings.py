"""The families' task-settings models, as config receives them from above.

Config is the bottom layer: it imports neither the family registry, nor the contract, nor any family. The registry
(:mod:`adaptdiffuser.family_registry`) hands config each family's settings model with :func:`register_family` when
it is imported, and the package's ``__init__`` imports the registry, so every family is registered before params
are read. Config asks for a model only when it validates or completes a task entry of that family.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

#: family name -> a function returning the model of that family's ``task.<name>`` entries (called only when such an
#: entry is read, so a family's settings module is imported only when one of its tasks is used)
_SETTINGS_MODELS: dict[str, Callable[[], type]] = {}


def register_family(name: str, settings_model: Callable[[], type]) -> None:
    """Make ``name`` a family config accepts, its task entries validated by the model ``settings_model()``."""
    _SETTINGS_MODELS[name] = settings_model


def family_names() -> list[str]:
    """The registered families, sorted."""
    return sorted(_SETTINGS_MODELS)


def is_family(value: Any) -> bool:
    """Whether ``value`` (the ``family`` key of an entry, as written) names a registered family."""
    return isinstance(value, str) and value in _SETTINGS_MODELS


def settings_model(name: str) -> type:
    """The model of family ``name``'s task entries; ``KeyError`` naming the registered families otherwise."""
    if name not in _SETTINGS_MODELS:
        raise KeyError(f"unknown family {name!r}; registered families: {family_names()}")
    return _SETTINGS_MODELS[name]()
