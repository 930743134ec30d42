"""Value types for params fields: YAML-friendly but strict numbers, and the range checks of each field.

Floats accept integers and YAML 1.1's ``2e-4`` (read as a string) and must be finite; integers accept an integral
float (``100.0``) but never ``10.5`` or ``true``; booleans and strings are strict (no ``"yes"``, no ``7``).
Every failure is a :class:`pydantic_core.PydanticCustomError` whose message reads well after the dotted key.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from typing import Annotated, Any

from pydantic import AfterValidator, BeforeValidator, Strict
from pydantic_core import PydanticCustomError

from adaptdiffuser.config.errors import show


def fail(message: str) -> PydanticCustomError:
    """A field error with this reason (the loader puts the dotted key in front)."""
    return PydanticCustomError("config", message)


def _to_float(value: Any) -> float:
    if isinstance(value, str):  # YAML 1.1 reads "2e-4" (no dot) as a string
        try:
            value = float(value)
        except ValueError:
            raise fail(f"must be a number, got {show(value)}") from None
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise fail(f"must be a number, got {show(value)}")
    value = float(value)
    if not math.isfinite(value):
        raise fail(f"must be a finite number, got {value}")
    return value


def _to_int(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise fail(f"must be an integer, got {show(value)}")
    if isinstance(value, numbers.Integral):
        return int(value)
    if not math.isfinite(value) or int(value) != value:
        raise fail(f"must be an integer, got {show(value)}")
    return int(value)


def requires(predicate: Callable[[Any], bool], requirement: str) -> AfterValidator:
    """A check: ``predicate(value)`` must hold, else the error reads ``must be <requirement>, got <value>``."""

    def check(value: Any) -> Any:
        if value is not None and not predicate(value):
            raise fail(f"must be {requirement}, got {show(value)}")
        return value

    return AfterValidator(check)


def one_of(*choices: str) -> AfterValidator:
    """The value must be one of ``choices``."""
    return requires(lambda v: v in choices, f"one of {', '.join(map(repr, choices))}")


POSITIVE = requires(lambda v: v > 0, "> 0")
NON_NEGATIVE = requires(lambda v: v >= 0, ">= 0")
UNIT = requires(lambda v: 0.0 <= v <= 1.0, "in [0, 1]")
UNIT_OPEN = requires(lambda v: 0.0 <= v < 1.0, "in [0, 1)")
FRACTION = requires(lambda v: 0.0 < v <= 1.0, "in (0, 1]")
HALF_CELL = requires(lambda v: 0.0 <= v < 0.5, "in [0, 0.5) (half a cell)")
ODD = requires(lambda v: v % 2 == 1, "odd")

Float = Annotated[float, BeforeValidator(_to_float)]
Int = Annotated[int, BeforeValidator(_to_int)]
Bool = Annotated[bool, Strict()]
Str = Annotated[str, Strict()]

PositiveFloat = Annotated[Float, POSITIVE]
NonNegativeFloat = Annotated[Float, NON_NEGATIVE]
PositiveInt = Annotated[Int, POSITIVE]
NonNegativeInt = Annotated[Int, NON_NEGATIVE]
Seed = Annotated[Int, NON_NEGATIVE]
Sampler = Annotated[Str, one_of("ddpm", "ddim")]
