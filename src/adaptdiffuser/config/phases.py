"""The evolution phase chain: ``phases`` maps ``phase<k>`` to ``{previous: j, <evolution overrides>}``, k = 1..K.

Each phase is the ``evolution`` defaults with its own overrides merged in (any evolution key may be overridden),
validated as a :class:`PhaseParams`; the chain must be phase1..phaseK without gaps and each phase must start
from an earlier one (0 is the pretrained model).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from typing import Any

from pydantic import TypeAdapter, ValidationError
from pydantic.dataclasses import dataclass

from adaptdiffuser.config.errors import ConfigError, config_error, show
from adaptdiffuser.config.fields import NonNegativeInt, Str
from adaptdiffuser.config.merge import deep_merge
from adaptdiffuser.config.sections import (
    SECTION,
    DiscriminateParams,
    EvolutionParams,
    FinetuneParams,
    GenerateParams,
)

PHASE_NAME = re.compile(r"phase([1-9][0-9]*)")
PHASE_KEYS = ("previous", "generate", "discriminate", "finetune")


@dataclass(frozen=True, config=SECTION)
class PhaseParams:
    """One evolution phase: its name (``phase<k>``), index k, the phase whose model it starts from, and the
    ``evolution`` sections with this phase's overrides merged in."""

    name: Str
    index: NonNegativeInt
    previous: NonNegativeInt
    generate: GenerateParams
    discriminate: DiscriminateParams
    finetune: FinetuneParams


_PHASE = TypeAdapter(PhaseParams)


def build_phases(raw: Any, evolution: EvolutionParams) -> tuple[PhaseParams, ...]:
    """The phases declared in ``raw`` (the ``phases`` mapping of params.yaml), sorted by index."""
    if raw is None:
        return ()
    if not isinstance(raw, Mapping):
        raise ConfigError(f"phases: must be a mapping like {{phase1: {{previous: 0}}}}, got {type(raw).__name__}")
    defaults = dataclasses.asdict(evolution)
    phases = []
    for name, entry in raw.items():
        where = f"phases.{name}"
        match = PHASE_NAME.fullmatch(str(name))
        if not match:
            raise ConfigError(f"{where}: phase names must be phase1, phase2, ...")
        if entry is None:
            entry = {}
        if not isinstance(entry, Mapping):
            raise ConfigError(
                f"{where}: must be a mapping like {{previous: 0}} (plus evolution overrides), got {show(entry)}"
            )
        unknown = sorted(str(key) for key in entry if key not in PHASE_KEYS)
        if unknown:
            raise ConfigError(f"{where}.{unknown[0]}: unknown key; known keys: {', '.join(PHASE_KEYS)}")
        if "previous" not in entry:
            raise ConfigError(f"{where}.previous: is required (the phase whose model it starts from)")
        overrides = {key: value for key, value in entry.items() if key != "previous"}
        values = {"name": str(name), "index": int(match.group(1)), "previous": entry["previous"]}
        try:
            phases.append(_PHASE.validate_python(values | deep_merge(defaults, overrides)))
        except ValidationError as err:
            raise config_error(err, PhaseParams, prefix=where) from None
    return tuple(sorted(phases, key=lambda phase: phase.index))


def check_chain(phases: tuple[PhaseParams, ...]) -> None:
    """Phases are phase1..phaseK without gaps, each starting from an earlier phase."""
    indices = [phase.index for phase in phases]
    if indices != list(range(1, len(phases) + 1)):
        raise ConfigError(f"phases: must be named phase1..phase{len(phases)} without gaps, got {indices}")
    for phase in phases:
        if phase.name != f"phase{phase.index}":
            raise ConfigError(f"phases.{phase.name}: the name does not match its index {phase.index}")
        if not phase.previous < phase.index:
            raise ConfigError(
                f"phases.{phase.name}.previous: must name an earlier phase (0..{phase.index - 1}), got {phase.previous}"
            )
