"""The whole of ``params.yaml``: every section, the phase chain and the checks that span sections."""

from __future__ import annotations

import dataclasses
from dataclasses import field
from typing import Any

from pydantic import ValidationInfo, field_validator, model_validator
from pydantic.dataclasses import dataclass

from adaptdiffuser.config.errors import ConfigError
from adaptdiffuser.config.fields import Float
from adaptdiffuser.config.phases import PhaseParams, build_phases, check_chain
from adaptdiffuser.config.sections import (
    SECTION,
    CollectParams,
    DiffusionParams,
    EnvParams,
    EvaluateParams,
    EvolutionParams,
    ExpertParams,
    GoldCoinParams,
    ModelParams,
    PlannerParams,
    PretrainParams,
)
from adaptdiffuser.config.sweep import SweepParams
from adaptdiffuser.envs.layouts import EPISODE_STEPS

PAPER_RULE_MAZES = ("umaze", "medium", "large")
CUSTOM_EPISODE_STEPS = 300  # what the simulator uses for a custom layout when env.episode_steps is null


@dataclass(frozen=True, config=SECTION)
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
    alpha: Float = 0.0
    phases: tuple[PhaseParams, ...] = ()  # from a mapping phase<k>: {previous: j, <evolution overrides>}
    sweep: SweepParams = field(default_factory=SweepParams)

    @field_validator("phases", mode="before")
    @classmethod
    def _build_phases(cls, value: Any, info: ValidationInfo) -> Any:
        if isinstance(value, tuple | list) and all(isinstance(phase, PhaseParams) for phase in value):
            return tuple(value)
        evolution = info.data.get("evolution")
        if evolution is None:  # evolution itself is invalid: that error is reported first
            return ()
        return build_phases(value, evolution)

    @field_validator("sweep", mode="before")
    @classmethod
    def _sweep_defaults(cls, value: Any) -> Any:
        return SweepParams() if value is None else value

    @model_validator(mode="after")
    def _cross_checks(self) -> Params:
        check_cross_fields(self)
        return self

    @property
    def task(self) -> str:
        """The task name (one MLflow experiment per task), e.g. ``maze2d-umaze``."""
        return f"maze2d-{self.env.maze}" if self.env.layout is None else "maze2d-custom"

    @property
    def episode_steps(self) -> int:
        """The episode length: ``env.episode_steps``, or the protocol's length for the maze when that is null."""
        if self.env.episode_steps is not None:
            return self.env.episode_steps
        if self.env.layout is not None:
            return CUSTOM_EPISODE_STEPS
        return EPISODE_STEPS.get(self.env.maze, CUSTOM_EPISODE_STEPS)

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


def check_cross_fields(p: Params) -> None:
    """The checks that span sections; :class:`ConfigError` naming the key."""
    factor = 2 ** (len(p.model.dim_mults) - 1)
    if p.diffusion.horizon % factor:
        raise ConfigError(
            f"diffusion.horizon: must be divisible by {factor} (the U-Net halves it {len(p.model.dim_mults) - 1} "
            f"times; see model.dim_mults), got {p.diffusion.horizon}"
        )
    if p.episode_steps < p.diffusion.horizon:
        h = p.diffusion.horizon
        if p.env.episode_steps is not None:
            raise ConfigError(f"env.episode_steps: {p.episode_steps} is shorter than diffusion.horizon={h}")
        raise ConfigError(
            f"env.episode_steps: null means the {p.task} protocol's {p.episode_steps} steps, shorter than "
            f"diffusion.horizon={h}; set env.episode_steps >= {h}"
        )
    if p.planner.sampler_steps > p.diffusion.n_steps:
        raise ConfigError(
            f"planner.sampler_steps: {p.planner.sampler_steps} exceeds diffusion.n_steps={p.diffusion.n_steps}"
        )
    check_chain(p.phases)
    paper_ok = p.env.layout is None and p.env.maze in PAPER_RULE_MAZES
    for phase in p.phases:
        where = f"phases.{phase.name}"
        g, d = phase.generate, phase.discriminate
        if g.sampler_steps > p.diffusion.n_steps:
            raise ConfigError(
                f"{where}.generate.sampler_steps: must be in 1..diffusion.n_steps={p.diffusion.n_steps}, "
                f"got {g.sampler_steps}"
            )
        if d.rule == "paper" and not paper_ok:
            raise ConfigError(
                f"{where}.discriminate.rule: the rule 'paper' has thresholds for umaze, medium and large only; "
                "for a custom layout set evolution.discriminate.rule to quantile or top_k"
            )
