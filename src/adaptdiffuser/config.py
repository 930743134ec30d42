"""The one config loader: ``params.yaml`` into typed, validated sections, and profile switching.

Every stage loads the whole file through :func:`load_params`, so a bad value anywhere is rejected before any
work starts, with a message naming the key (for example ``pretrain.steps``).
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from adaptdiffuser.envs.layouts import MAZES, parse_layout
from adaptdiffuser.io import atomic_path


class ConfigError(ValueError):
    """A params value is missing, unknown or invalid; the message names the key."""


SELECTION_RULES = ("paper", "quantile", "top_k")


@dataclass(frozen=True)
class EnvParams:
    maze: str = "umaze"
    layout: list[str] | None = None
    episode_steps: int | None = None
    goal_radius: float = 0.5
    reset_pos_noise: float = 0.1
    reset_vel_noise: float = 0.1
    random_goal: bool = False


@dataclass(frozen=True)
class ExpertParams:
    p_gain: float = 10.0
    d_gain: float = 1.0
    jitter: float = 0.2
    waypoint_radius: float = 0.3


@dataclass(frozen=True)
class CollectParams:
    steps: int = 200_000
    seed: int = 0


@dataclass(frozen=True)
class ModelParams:
    dim: int = 16
    dim_mults: list[int] = field(default_factory=lambda: [1, 4, 8])
    kernel_size: int = 5


@dataclass(frozen=True)
class DiffusionParams:
    horizon: int = 128
    n_steps: int = 64
    predict_epsilon: bool = False
    clip_denoised: bool = True
    action_weight: float = 1.0
    loss_discount: float = 1.0


@dataclass(frozen=True)
class PretrainParams:
    steps: int = 8000
    batch_size: int = 32
    grad_accum: int = 1
    lr: float = 2e-4
    ema_decay: float = 0.995
    ema_every: int = 10
    ema_start: int = 500
    log_every: int = 100
    checkpoint_every: int = 1000
    seed: int = 0
    expert_fraction: float = 1.0


@dataclass(frozen=True)
class GoldCoinParams:
    cases_per_kind: int = 10
    seed: int = 2000
    radius: float = 0.5
    batch_size: int = 50
    pictures: int = 3


@dataclass(frozen=True)
class SearchDimension:
    """One entry of ``sweep.space``: a params key (dotted) and the range Optuna samples it from."""

    key: str
    kind: str  # float | int | categorical
    low: float | None = None
    high: float | None = None
    log: bool = False
    choices: tuple = ()


@dataclass(frozen=True)
class SweepParams:
    study: str = "adaptdiffuser"
    trials: int = 4
    workers: int = 2
    seed: int = 0
    objective: str = "mix"
    coin_weight: float = 0.5
    storage: str | None = None
    heartbeat_s: int = 30
    pruner_startup_trials: int = 1
    space: tuple[SearchDimension, ...] = ()


@dataclass(frozen=True)
class GenerateParams:
    tasks: int = 1024
    batch_size: int = 128
    seed: int = 100
    sampler: str = "ddim"
    sampler_steps: int = 16
    cell_spread: float = 0.4
    coin_fraction: float = 0.0


@dataclass(frozen=True)
class DiscriminateParams:
    tracking: bool = True
    max_error: float = 1.0
    rule: str = "paper"
    quantile: float = 0.5
    top_k: int = 64


@dataclass(frozen=True)
class FinetuneParams:
    steps_fraction: float = 0.25
    expert_weight: float = 0.5
    seed: int = 1


@dataclass(frozen=True)
class EvolutionParams:
    generate: GenerateParams = field(default_factory=GenerateParams)
    discriminate: DiscriminateParams = field(default_factory=DiscriminateParams)
    finetune: FinetuneParams = field(default_factory=FinetuneParams)


@dataclass(frozen=True)
class PhaseParams:
    """One evolution phase: its name (``phase<k>``), index k, the phase whose model it starts from, and the
    ``evolution`` sections with this phase's overrides merged in."""

    name: str
    index: int
    previous: int
    generate: GenerateParams
    discriminate: DiscriminateParams
    finetune: FinetuneParams


@dataclass(frozen=True)
class PlannerParams:
    sampler: str = "ddim"
    sampler_steps: int = 16
    replan_every: int = 0
    tracking_p_gain: float = 2.0
    tracking_d_gain: float = 0.5


@dataclass(frozen=True)
class EvaluateParams:
    episodes: int = 50
    seed: int = 1000
    batch_size: int = 50
    pictures: int = 4


@dataclass(frozen=True)
class Params:
    env: EnvParams = field(default_factory=EnvParams)
    expert: ExpertParams = field(default_factory=ExpertParams)
    collect: CollectParams = field(default_factory=CollectParams)
    model: ModelParams = field(default_factory=ModelParams)
    diffusion: DiffusionParams = field(default_factory=DiffusionParams)
    pretrain: PretrainParams = field(default_factory=PretrainParams)
    planner: PlannerParams = field(default_factory=PlannerParams)
    evaluate: EvaluateParams = field(default_factory=EvaluateParams)
    evolution: EvolutionParams = field(default_factory=EvolutionParams)
    gold_coin: GoldCoinParams = field(default_factory=GoldCoinParams)
    alpha: float = 0.0
    phases: tuple[PhaseParams, ...] = ()
    sweep: SweepParams = field(default_factory=SweepParams)

    @property
    def task(self) -> str:
        """The task name (one MLflow experiment per task), e.g. ``maze2d-umaze``."""
        return f"maze2d-{self.env.maze}" if self.env.layout is None else "maze2d-custom"

    def section(self, name: str) -> dict[str, Any]:
        """One params section as a plain dict (for logging)."""
        return dataclasses.asdict(getattr(self, name))

    def phase(self, index: int) -> PhaseParams:
        """The evolution phase ``index`` (1..K); :class:`ConfigError` if params.yaml does not declare it."""
        for phase in self.phases:
            if phase.index == index:
                return phase
        raise ConfigError(f"phase {index} is not declared under 'phases' in params (have {self.phase_names})")

    @property
    def phase_names(self) -> list[str]:
        return [phase.name for phase in self.phases]

    def lineage(self, index: int) -> list[int]:
        """The evolution phases whose selected data trains phase ``index``: it and its ancestors, oldest first."""
        chain = []
        while index > 0:
            chain.append(index)
            index = self.phase(index).previous
        return chain[::-1]


def load_params(path: str | Path = "params.yaml") -> Params:
    """Load and validate ``params.yaml``; raise :class:`ConfigError` naming the first bad key."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"params file not found: {path}")
    raw = yaml.safe_load(path.read_text()) or {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: top level must be a mapping of sections")
    return params_from_dict(raw)


def params_from_dict(raw: dict[str, Any]) -> Params:
    """Build and validate params from the parsed YAML mapping (which is left unchanged)."""
    raw = dict(raw)
    phases_raw = raw.pop("phases", None) or {}
    sweep_raw = raw.pop("sweep", None) or {}
    params = _build(Params, raw, prefix="")
    evolution_raw = raw.get("evolution") or {}
    params = dataclasses.replace(params, phases=_build_phases(phases_raw, evolution_raw), sweep=_build_sweep(sweep_raw))
    validate(params)
    _validate_sweep_space(raw | {"phases": phases_raw}, params.sweep)
    return params


SWEEP_OBJECTIVES = ("navigation", "coin", "mix")


def _build_sweep(raw: Any) -> SweepParams:
    if not isinstance(raw, dict):
        raise ConfigError(f"sweep must be a mapping, got {type(raw).__name__}")
    raw = dict(raw)
    space_raw = raw.pop("space", None) or {}
    sweep = _build(SweepParams, raw, prefix="sweep.")
    if not isinstance(space_raw, dict):
        raise ConfigError("sweep.space must map params keys to ranges, e.g. {alpha: {low: 1, high: 100, log: true}}")
    dims = []
    for key, spec in space_raw.items():
        where = f"sweep.space.{key}"
        if not isinstance(spec, dict):
            raise ConfigError(f"{where} must be a mapping like {{low: 1, high: 10}} or {{choices: [a, b]}}")
        unknown = set(spec) - {"low", "high", "log", "int", "choices"}
        if unknown:
            raise ConfigError(f"{where}: unknown field {sorted(unknown)[0]!r} (use low, high, log, int or choices)")
        if "choices" in spec:
            choices = spec["choices"]
            if not isinstance(choices, list) or not choices:
                raise ConfigError(f"{where}.choices must be a non-empty list")
            dims.append(SearchDimension(str(key), "categorical", choices=tuple(choices)))
            continue
        if "low" not in spec or "high" not in spec:
            raise ConfigError(f"{where} needs low and high (or choices)")
        low = _coerce(spec["low"], float, f"{where}.low")
        high = _coerce(spec["high"], float, f"{where}.high")
        log = _coerce(spec.get("log", False), bool, f"{where}.log")
        is_int = _coerce(spec.get("int", False), bool, f"{where}.int")
        if not low < high:
            raise ConfigError(f"{where}: low ({low:g}) must be below high ({high:g})")
        if log and low <= 0:
            raise ConfigError(f"{where}: a log range needs low > 0, got {low:g}")
        dims.append(SearchDimension(str(key), "int" if is_int else "float", low, high, log))
    if sweep.trials <= 0 or sweep.workers <= 0:
        raise ConfigError(f"sweep.trials and sweep.workers must be > 0, got {sweep.trials} and {sweep.workers}")
    if sweep.objective not in SWEEP_OBJECTIVES:
        raise ConfigError(f"sweep.objective must be one of {SWEEP_OBJECTIVES}, got {sweep.objective!r}")
    if not 0.0 <= sweep.coin_weight <= 1.0:
        raise ConfigError(f"sweep.coin_weight must be in [0, 1], got {sweep.coin_weight}")
    return dataclasses.replace(sweep, space=tuple(dims))


def set_dotted(raw: dict[str, Any], key: str, value: Any) -> dict[str, Any]:
    """A deep copy of ``raw`` with the dotted ``key`` (e.g. ``evolution.discriminate.max_error``) set."""
    import copy

    out = copy.deepcopy(raw)
    node = out
    parts = key.split(".")
    for part in parts[:-1]:
        if not isinstance(node.get(part), dict):
            node[part] = {}
        node = node[part]
    node[parts[-1]] = value
    return out


def _validate_sweep_space(raw: dict[str, Any], sweep: SweepParams) -> None:
    """Every search key must name an existing params value, and both ends of its range must be valid params."""
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
                params_from_dict(trial_raw)
            except ConfigError as err:
                raise ConfigError(f"sweep.space.{dim.key}: the value {value!r} is not valid: {err}") from None


_PHASE_NAME = re.compile(r"phase([1-9][0-9]*)")


def _build_phases(raw: Any, evolution: dict[str, Any]) -> tuple[PhaseParams, ...]:
    """``phases`` is a mapping ``phase<k>: {previous: j, <evolution overrides>}``, k = 1..K."""
    if not isinstance(raw, dict):
        raise ConfigError(f"phases must be a mapping like {{phase1: {{previous: 0}}}}, got {type(raw).__name__}")
    phases = []
    for name, entry in raw.items():
        match = _PHASE_NAME.fullmatch(str(name))
        if not match:
            raise ConfigError(f"phases.{name}: phase names must be phase1, phase2, ...")
        entry = dict(entry or {})
        if "previous" not in entry:
            raise ConfigError(f"phases.{name}.previous is required (the phase whose model it starts from)")
        previous = _coerce(entry.pop("previous"), int, f"phases.{name}.previous")
        merged = _build(EvolutionParams, deep_merge(evolution, entry), prefix=f"phases.{name}.")
        phases.append(
            PhaseParams(
                name=str(name),
                index=int(match.group(1)),
                previous=previous,
                generate=merged.generate,
                discriminate=merged.discriminate,
                finetune=merged.finetune,
            )
        )
    phases.sort(key=lambda phase: phase.index)
    indices = [phase.index for phase in phases]
    if indices != list(range(1, len(phases) + 1)):
        raise ConfigError(f"phases must be named phase1..phase{len(phases)} without gaps, got {indices}")
    for phase in phases:
        if not 0 <= phase.previous < phase.index:
            raise ConfigError(
                f"phases.{phase.name}.previous={phase.previous} must name an earlier phase (0..{phase.index - 1})"
            )
    return tuple(phases)


def validate(p: Params) -> None:
    """Cross-field checks that types alone cannot express."""
    if p.env.layout is not None:
        try:
            parse_layout(p.env.layout)
        except ValueError as err:
            raise ConfigError(f"env.layout: {err}") from err
    elif p.env.maze not in MAZES:
        raise ConfigError(f"env.maze: unknown maze {p.env.maze!r}; choose one of {sorted(MAZES)}")
    _positive(p, "env.episode_steps", allow_none=True)
    _positive(p, "env.goal_radius")
    _non_negative(p, "env.reset_pos_noise", "env.reset_vel_noise", "expert.jitter")
    _positive(p, "expert.p_gain", "expert.waypoint_radius", "collect.steps")
    _positive(p, "model.dim", "model.kernel_size")
    if not p.model.dim_mults or any(m <= 0 for m in p.model.dim_mults):
        raise ConfigError("model.dim_mults must be a non-empty list of positive integers")
    if p.model.kernel_size % 2 == 0:
        raise ConfigError(f"model.kernel_size must be odd, got {p.model.kernel_size}")
    _positive(p, "diffusion.horizon", "diffusion.n_steps", "diffusion.action_weight", "diffusion.loss_discount")
    factor = 2 ** (len(p.model.dim_mults) - 1)
    if p.diffusion.horizon % factor:
        raise ConfigError(
            f"diffusion.horizon={p.diffusion.horizon} must be divisible by {factor} "
            f"(the U-Net halves it {len(p.model.dim_mults) - 1} times; see model.dim_mults)"
        )
    _positive(p, "pretrain.steps", "pretrain.batch_size", "pretrain.grad_accum", "pretrain.lr")
    _positive(p, "pretrain.ema_every", "pretrain.log_every", "pretrain.checkpoint_every")
    _non_negative(p, "pretrain.ema_start")
    if not 0.0 <= p.pretrain.ema_decay < 1.0:
        raise ConfigError(f"pretrain.ema_decay must be in [0, 1), got {p.pretrain.ema_decay}")
    if p.planner.sampler not in ("ddpm", "ddim"):
        raise ConfigError(f"planner.sampler must be 'ddpm' or 'ddim', got {p.planner.sampler!r}")
    _positive(p, "planner.sampler_steps", "planner.tracking_p_gain")
    _non_negative(p, "planner.tracking_d_gain")
    if p.planner.sampler_steps > p.diffusion.n_steps:
        raise ConfigError(
            f"planner.sampler_steps={p.planner.sampler_steps} exceeds diffusion.n_steps={p.diffusion.n_steps}"
        )
    _non_negative(p, "planner.replan_every", "evaluate.pictures")
    _positive(p, "evaluate.episodes", "evaluate.batch_size")
    if not 0.0 < p.pretrain.expert_fraction <= 1.0:
        raise ConfigError(f"pretrain.expert_fraction must be in (0, 1], got {p.pretrain.expert_fraction}")
    _positive(p, "gold_coin.cases_per_kind", "gold_coin.radius", "gold_coin.batch_size")
    _non_negative(p, "gold_coin.pictures")
    if not math.isfinite(p.alpha):
        raise ConfigError(f"alpha must be a finite number, got {p.alpha}")
    for phase in p.phases:
        _validate_phase(p, phase)


def _validate_phase(p: Params, phase: PhaseParams) -> None:
    where = f"phases.{phase.name}"
    g, d, f = phase.generate, phase.discriminate, phase.finetune
    for key, value in [("generate.tasks", g.tasks), ("generate.batch_size", g.batch_size)]:
        if value <= 0:
            raise ConfigError(f"{where}.{key} (or evolution.{key}) must be > 0, got {value}")
    if g.sampler not in ("ddpm", "ddim"):
        raise ConfigError(f"{where}.generate.sampler must be 'ddpm' or 'ddim', got {g.sampler!r}")
    if not 0 < g.sampler_steps <= p.diffusion.n_steps:
        raise ConfigError(
            f"{where}.generate.sampler_steps={g.sampler_steps} must be in 1..diffusion.n_steps={p.diffusion.n_steps}"
        )
    if not 0.0 <= g.coin_fraction <= 1.0:
        raise ConfigError(f"{where}.generate.coin_fraction must be in [0, 1], got {g.coin_fraction}")
    if not 0.0 <= g.cell_spread < 0.5:
        raise ConfigError(f"{where}.generate.cell_spread must be in [0, 0.5) (half a cell), got {g.cell_spread}")
    if d.max_error <= 0:
        raise ConfigError(f"{where}.discriminate.max_error must be > 0, got {d.max_error}")
    if d.rule not in SELECTION_RULES:
        raise ConfigError(f"{where}.discriminate.rule must be one of {SELECTION_RULES}, got {d.rule!r}")
    if d.rule == "paper" and (p.env.layout is not None or p.env.maze not in ("umaze", "medium", "large")):
        raise ConfigError(
            f"{where}.discriminate.rule 'paper' has thresholds for umaze, medium and large only; "
            "for a custom layout set evolution.discriminate.rule to quantile or top_k"
        )
    if not 0.0 <= d.quantile <= 1.0:
        raise ConfigError(f"{where}.discriminate.quantile must be in [0, 1], got {d.quantile}")
    if d.top_k <= 0:
        raise ConfigError(f"{where}.discriminate.top_k must be > 0, got {d.top_k}")
    if f.steps_fraction <= 0:
        raise ConfigError(f"{where}.finetune.steps_fraction must be > 0, got {f.steps_fraction}")
    if not 0.0 <= f.expert_weight < 1.0:
        raise ConfigError(f"{where}.finetune.expert_weight must be in [0, 1), got {f.expert_weight}")


def _get(p: Params, dotted: str) -> Any:
    value: Any = p
    for part in dotted.split("."):
        value = getattr(value, part)
    return value


def _positive(p: Params, *keys: str, allow_none: bool = False) -> None:
    for key in keys:
        value = _get(p, key)
        if value is None and allow_none:
            continue
        if value is None or value <= 0:
            raise ConfigError(f"{key} must be > 0, got {value}")


def _non_negative(p: Params, *keys: str) -> None:
    for key in keys:
        value = _get(p, key)
        if value < 0:
            raise ConfigError(f"{key} must be >= 0, got {value}")


def _build(cls: type, raw: Any, prefix: str) -> Any:
    if not isinstance(raw, dict):
        raise ConfigError(f"{prefix.rstrip('.') or 'params'} must be a mapping, got {type(raw).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(raw) - names)
    if unknown:
        raise ConfigError(f"unknown params key {prefix}{unknown[0]}; known keys: {sorted(names)}")
    values = {}
    for name in names & set(raw):
        hint = hints[name]
        key = f"{prefix}{name}"
        if dataclasses.is_dataclass(hint):
            values[name] = _build(hint, raw[name], prefix=f"{key}.")
        else:
            values[name] = _coerce(raw[name], hint, key)
    return cls(**values)


def _coerce(value: Any, hint: Any, key: str) -> Any:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(value, inner[0], key)
    if origin is list:
        if not isinstance(value, list):
            raise ConfigError(f"{key} must be a list, got {value!r}")
        return [_coerce(v, args[0], f"{key}[{i}]") for i, v in enumerate(value)]
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key} must be true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int | float) or int(value) != value:
            raise ConfigError(f"{key} must be an integer, got {value!r}")
        return int(value)
    if hint is float:
        if isinstance(value, str):  # YAML 1.1 reads "2e-4" (no dot) as a string
            try:
                value = float(value)
            except ValueError:
                raise ConfigError(f"{key} must be a number, got {value!r}") from None
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{key} must be a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key} must be a string, got {value!r}")
        return value
    raise ConfigError(f"{key}: unsupported type {hint}")


def deep_merge(base: dict, overlay: dict) -> dict:
    """``base`` with ``overlay`` merged in, recursively for nested mappings."""
    merged = dict(base)
    for key, value in overlay.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def apply_profile(profile: str, profiles_dir: str | Path = "profiles", params_path: str | Path = "params.yaml") -> Path:
    """Write ``params.yaml`` as the quick profile overlaid with ``profiles/<profile>.yaml``; validate first."""
    profiles_dir = Path(profiles_dir)
    base_path = profiles_dir / "quick.yaml"
    overlay_path = profiles_dir / f"{profile}.yaml"
    if not overlay_path.exists():
        known = sorted(p.stem for p in profiles_dir.glob("*.yaml"))
        raise ConfigError(f"unknown profile {profile!r}; known profiles: {known}")
    base_text = base_path.read_text()
    base = yaml.safe_load(base_text) or {}
    merged = deep_merge(base, yaml.safe_load(overlay_path.read_text()) or {})
    if merged == base:  # the quick profile itself: keep its comments
        text = base_text
    else:
        header = f"# Written by `adaptdiffuser profile {profile}`: profiles/quick.yaml + profiles/{profile}.yaml\n"
        text = header + yaml.safe_dump(merged, sort_keys=False)
    params_path = Path(params_path)
    with atomic_path(params_path) as tmp:
        tmp.write_text(text)
        load_params(tmp)
    return params_path
