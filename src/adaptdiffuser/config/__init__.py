"""The one config loader: ``params.yaml`` into typed, validated sections (pydantic models), and profile switching.

Every stage loads the whole file through :func:`load_params`, so a bad value anywhere is rejected before any
work starts, with a one-line :class:`ConfigError` naming the key (for example ``pretrain.lr: must be a finite
number, got nan``).

Every default is stated once, by these classes (and each family's task model); the profiles are overlays over them
and ``params.yaml`` is a profile resolved, every value written (:func:`apply_profile`).

Modules: ``fields`` (value types and range checks), ``sections`` (one model per generic section), ``tasks`` (task
entries, resolved with their family's model), ``phases`` (the phase chain), ``sweep_settings`` (sweep settings and
search space), ``value_settings`` (a locomotion task's value function), ``params`` (the whole file and its
cross-section checks), ``loader`` (YAML in, :class:`ConfigError` out), ``defaults`` (the classes' defaults as a
params file writes them), ``profiles`` (profile switching), ``tiny`` (any profile at tiny scale), ``describe`` (what
will run).
"""

from adaptdiffuser.config.describe import describe, stage_names
from adaptdiffuser.config.errors import ConfigError
from adaptdiffuser.config.loader import load_params, params_from_dict
from adaptdiffuser.config.merge import deep_merge
from adaptdiffuser.config.params import Params, check_cross_fields
from adaptdiffuser.config.phases import PhaseParams
from adaptdiffuser.config.profiles import apply_profile
from adaptdiffuser.config.sections import (
    SELECTION_RULES,
    CompileParams,
    DiffusionParams,
    DiscriminateParams,
    EvaluateParams,
    EvolutionParams,
    FinetuneParams,
    GenerateParams,
    ModelParams,
    PlannerParams,
    PretrainParams,
)
from adaptdiffuser.config.sweep_settings import SWEEP_OBJECTIVES, SearchDimension, SweepParams, set_dotted
from adaptdiffuser.config.tasks import GENERIC_SECTIONS, TaskParams

__all__ = [
    "GENERIC_SECTIONS",
    "SELECTION_RULES",
    "SWEEP_OBJECTIVES",
    "CompileParams",
    "ConfigError",
    "DiffusionParams",
    "DiscriminateParams",
    "EvaluateParams",
    "EvolutionParams",
    "FinetuneParams",
    "GenerateParams",
    "ModelParams",
    "Params",
    "PhaseParams",
    "PlannerParams",
    "PretrainParams",
    "SearchDimension",
    "SweepParams",
    "TaskParams",
    "apply_profile",
    "check_cross_fields",
    "deep_merge",
    "describe",
    "load_params",
    "params_from_dict",
    "set_dotted",
    "stage_names",
]
