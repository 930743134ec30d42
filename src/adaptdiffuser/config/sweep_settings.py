"""The ``sweep`` section: Optuna settings and the search space over other params keys."""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping
from dataclasses import field
from typing import Annotated, Any

from pydantic import TypeAdapter, ValidationError, field_validator
from pydantic.dataclasses import dataclass

from adaptdiffuser.config.errors import ConfigError, config_error, show
from adaptdiffuser.config.fields import (
    UNIT,
    Bool,
    Float,
    NonNegativeInt,
    PositiveInt,
    Seed,
    Str,
    one_of,
)
from adaptdiffuser.config.sections import SECTION

SWEEP_OBJECTIVES = ("gain", "score", "unseen", "mix")
SEARCH_KINDS = ("float", "int", "categorical")


@dataclass(frozen=True, config=SECTION)
class SearchDimension:
    """One entry of ``sweep.space``: a params key (dotted) and the range Optuna samples it from."""

    key: Str
    kind: Annotated[Str, one_of(*SEARCH_KINDS)]  # float | int | categorical
    low: Float | None = None
    high: Float | None = None
    log: Bool = False
    choices: tuple[Any, ...] = ()


@dataclass(frozen=True, config=SECTION)
class _RangeSpec:
    """How a ``sweep.space`` entry is written: ``{low, high, log?, int?}`` or ``{choices: [...]}``."""

    low: Float | None = None
    high: Float | None = None
    log: Bool = False
    int: Bool = False
    choices: list[Any] | None = None


_SPEC = TypeAdapter(_RangeSpec)


def search_dimension(key: str, spec: Any) -> SearchDimension:
    """Parse one ``sweep.space`` entry; :class:`ConfigError` naming ``sweep.space.<key>`` when it is malformed."""
    where = f"sweep.space.{key}"
    if not isinstance(spec, Mapping):
        raise ConfigError(f"{where}: must be a mapping like {{low: 1, high: 10}} or {{choices: [a, b]}}")
    try:
        s = _SPEC.validate_python(dict(spec))
    except ValidationError as err:
        if err.errors()[0]["type"] == "unexpected_keyword_argument":
            bad = err.errors()[0]["loc"][-1]
            raise ConfigError(f"{where}: unknown field {bad!r} (use low, high, log, int or choices)") from None
        raise config_error(err, _RangeSpec, prefix=where) from None
    if s.choices is not None:
        if not s.choices:
            raise ConfigError(f"{where}.choices: must be a non-empty list")
        return SearchDimension(str(key), "categorical", choices=tuple(s.choices))
    if s.low is None or s.high is None:
        raise ConfigError(f"{where}: needs low and high (or choices)")
    if not s.low < s.high:
        raise ConfigError(f"{where}: low ({s.low:g}) must be below high ({s.high:g})")
    if s.log and s.low <= 0:
        raise ConfigError(f"{where}: a log range needs low > 0, got {s.low:g}")
    return SearchDimension(str(key), "int" if s.int else "float", s.low, s.high, s.log)


@dataclass(frozen=True, config=SECTION)
class SweepParams:
    """``adaptdiffuser sweep``: Optuna over the keys of ``space`` (phase 0 is reused, never retrained)."""

    study: Str = "adaptdiffuser"
    task: Str | None = None  # the task whose evolution phases the trials run; null = `evolve`
    trials: PositiveInt = 4
    workers: PositiveInt = 2
    seed: Seed = 0
    #: gain (final phase - its control) | score | unseen (the unseen task's figure, 0-100) | mix of score and unseen
    objective: Annotated[Str, one_of(*SWEEP_OBJECTIVES)] = "gain"
    #: the trials' start states (plus training seed): their evaluation set and their held-out one, never the
    #: pipeline's (evaluate.seed, evaluate.held_out_seed) nor evaluate-kept's (config/start_states.py)
    evaluate_seed: Seed = 5000
    held_out_seed: Seed = 6000
    #: mix = (1 - w) x score + w x unseen
    unseen_weight: Annotated[Float, UNIT] = 0.5
    #: None = journal file sweeps/<study>.journal; or postgresql://user@host/db
    storage: Str | None = None
    #: RDB storages: a trial silent this long (x2) is failed and retried once
    heartbeat_s: PositiveInt = 30
    #: median pruning after each phase, once this many trials completed
    pruner_startup_trials: NonNegativeInt = 1
    #: params key: {low, high, log?, int?} or {choices: [...]}
    space: tuple[SearchDimension, ...] = field(default=())

    @field_validator("space", mode="before")
    @classmethod
    def _parse_space(cls, value: Any) -> Any:
        if value is None:
            return ()
        if isinstance(value, Mapping):
            return tuple(search_dimension(str(key), spec) for key, spec in value.items())
        if isinstance(value, tuple | list) and all(isinstance(dim, SearchDimension) for dim in value):
            return tuple(value)
        raise ConfigError(
            f"sweep.space: must map params keys to ranges, e.g. {{alpha: {{low: 1, high: 100, log: true}}}}, "
            f"got {show(value)}"
        )


def set_dotted(raw: dict[str, Any], key: str, value: Any) -> dict[str, Any]:
    """A deep copy of ``raw`` with the dotted ``key`` (e.g. ``evolution.discriminate.max_error``) set."""
    out = copy.deepcopy(raw)
    node = out
    parts = key.split(".")
    for part in parts[:-1]:
        if not isinstance(node.get(part), dict):
            node[part] = {}
        node = node[part]
    node[parts[-1]] = value
    return out


def check_space(raw: dict[str, Any], sweep: SweepParams, validate: Callable[[dict[str, Any]], Any]) -> None:
    """Every search key must name an existing params value, and both ends of its range (every choice) must give
    valid params; ``validate`` is :func:`adaptdiffuser.config.params_from_dict`."""
    for dim in sweep.space:
        node: Any = raw
        for part in dim.key.split("."):
            if not isinstance(node, dict) or part not in node:
                raise ConfigError(f"sweep.space.{dim.key}: no such key in params")
            node = node[part]
        ends = list(dim.choices) if dim.kind == "categorical" else [dim.low, dim.high]
        for value in ends:
            if dim.kind == "int":
                value = int(value)
            trial_raw = set_dotted(raw, dim.key, value)
            trial_raw.pop("sweep", None)
            try:
                validate(trial_raw)
            except ConfigError as err:
                raise ConfigError(f"sweep.space.{dim.key}: the value {value!r} is not valid: {err}") from None
