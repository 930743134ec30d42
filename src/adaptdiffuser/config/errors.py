"""The one error type of the config package, and turning pydantic's errors into it."""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

from pydantic import ValidationError


class ConfigError(ValueError):
    """A params value is missing, unknown or invalid; the one-line message names the key."""


def show(value: Any) -> str:
    """A value as an error message quotes it (``'fast'``, ``nan``, ``[1, 0]``)."""
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def dotted(loc: tuple[Any, ...], prefix: str = "") -> str:
    """``('model', 'dim_mults', 1)`` as ``model.dim_mults[1]``, under ``prefix`` (e.g. ``phases.phase1``)."""
    key = prefix
    for part in loc:
        if isinstance(part, int):
            key += f"[{part}]"
        else:
            key = f"{key}.{part}" if key else str(part)
    return key


def _known_keys(root: type | None, loc: tuple[Any, ...]) -> list[str]:
    """The field names of the dataclass reached from ``root`` by the string parts of ``loc``."""
    cls: Any = root
    for part in loc:
        if isinstance(part, int) or cls is None:
            continue
        if not dataclasses.is_dataclass(cls):
            return []
        hint = typing.get_type_hints(cls, include_extras=False).get(str(part))
        cls = _dataclass_in(hint)
    return sorted(f.name for f in dataclasses.fields(cls) if f.init) if dataclasses.is_dataclass(cls) else []


def _dataclass_in(hint: Any) -> type | None:
    if dataclasses.is_dataclass(hint):
        return hint
    for arg in typing.get_args(hint):
        found = _dataclass_in(arg)
        if found is not None:
            return found
    return None


_TYPE_REASONS = {
    "bool_type": "must be true or false",
    "bool_parsing": "must be true or false",
    "string_type": "must be a string",
    "list_type": "must be a list",
    "tuple_type": "must be a list",
    "int_type": "must be an integer",
    "float_type": "must be a number",
    "dict_type": "must be a mapping",
    "dataclass_type": "must be a mapping",
    "model_type": "must be a mapping",
}


def reason(error: dict[str, Any], root: type | None = None) -> str:
    """One pydantic error as ``key: reason`` (or the message of a :class:`ConfigError` raised in a validator)."""
    cause = (error.get("ctx") or {}).get("error")
    if isinstance(cause, ConfigError):  # raised by our own validators: already names its key
        return str(cause)
    loc = tuple(error["loc"])
    kind = error["type"]
    if kind in ("unexpected_keyword_argument", "extra_forbidden"):
        known = _known_keys(root, loc[:-1])
        return "unknown key" + (f"; known keys: {', '.join(known)}" if known else "")
    if kind == "missing":
        return "is required"
    if kind in _TYPE_REASONS:
        return f"{_TYPE_REASONS[kind]}, got {show(error.get('input'))}"
    message = str(error["msg"])
    return message.removeprefix("Value error, ").removeprefix("Assertion failed, ")


def config_error(err: ValidationError, root: type | None = None, prefix: str = "") -> ConfigError:
    """The first error of ``err`` as a one-line :class:`ConfigError` ``<dotted key>: <reason>``."""
    error = err.errors()[0]
    text = reason(error, root)
    cause = (error.get("ctx") or {}).get("error")
    if not isinstance(cause, ConfigError):
        key = dotted(tuple(error["loc"]), prefix) or "params"
        text = f"{key}: {text}"
    return ConfigError(" ".join(text.split()))
