"""The settings of a Maze2D task (``task.<name>`` with ``family: maze2d`` in params.yaml)."""

from __future__ import annotations

from dataclasses import field
from typing import TYPE_CHECKING, ClassVar, Literal

from pydantic import ValidationInfo, field_validator
from pydantic.dataclasses import dataclass

from adaptdiffuser.config.errors import ConfigError
from adaptdiffuser.config.fields import (
    Bool,
    Float,
    NonNegativeFloat,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    Seed,
    Str,
)
from adaptdiffuser.config.sections import SECTION
from adaptdiffuser.families.maze2d.layouts import EPISODE_STEPS, MAZES, parse_layout

if TYPE_CHECKING:
    from adaptdiffuser.config.params import Params
    from adaptdiffuser.config.tasks import TaskParams

PAPER_RULE_MAZES = ("umaze", "medium", "large")
CUSTOM_EPISODE_STEPS = 300  # what the simulator uses for a custom layout when env.episode_steps is null


@dataclass(frozen=True, config=SECTION)
class EnvParams:
    layout: list[Str] | None = None
    maze: Str = "umaze"
    episode_steps: PositiveInt | None = None
    goal_radius: PositiveFloat = 0.5
    reset_pos_noise: NonNegativeFloat = 0.1
    reset_vel_noise: NonNegativeFloat = 0.1
    random_goal: Bool = False

    @field_validator("layout")
    @classmethod
    def _layout_parses(cls, layout: list[str] | None) -> list[str] | None:
        if layout is not None:
            parse_layout(layout)  # its ValueError names the problem
        return layout

    @field_validator("maze")
    @classmethod
    def _maze_exists(cls, maze: str, info: ValidationInfo) -> str:
        if info.data.get("layout") is None and maze not in MAZES:
            raise ValueError(f"unknown maze {maze!r}; choose one of {sorted(MAZES)}")
        return maze


@dataclass(frozen=True, config=SECTION)
class ExpertParams:
    p_gain: PositiveFloat = 10.0
    d_gain: Float = 1.0
    jitter: NonNegativeFloat = 0.2
    waypoint_radius: PositiveFloat = 0.3


@dataclass(frozen=True, config=SECTION)
class CollectParams:
    steps: PositiveInt = 200_000
    seed: Seed = 0


@dataclass(frozen=True, config=SECTION)
class GoldCoinParams:
    cases_per_kind: PositiveInt = 10
    seed: Seed = 2000
    radius: PositiveFloat = 0.5
    batch_size: PositiveInt = 50
    pictures: NonNegativeInt = 3


@dataclass(frozen=True, config=SECTION)
class Maze2DTaskParams:
    """A Maze2D task: the maze and its protocol (``env``), the waypoint expert, data collection and the unseen
    gold-coin evaluation."""

    OPTIONAL_STAGES: ClassVar[tuple[str, ...]] = ("coin", "evolve")

    family: Literal["maze2d"] = "maze2d"
    env: EnvParams = field(default_factory=EnvParams)
    expert: ExpertParams = field(default_factory=ExpertParams)
    collect: CollectParams = field(default_factory=CollectParams)
    gold_coin: GoldCoinParams = field(default_factory=GoldCoinParams)

    @property
    def maze_name(self) -> str:
        return self.env.maze if self.env.layout is None else "custom"

    @property
    def episode_steps(self) -> int:
        """``env.episode_steps``, or the protocol's length for the maze when that is null."""
        if self.env.episode_steps is not None:
            return self.env.episode_steps
        if self.env.layout is not None:
            return CUSTOM_EPISODE_STEPS
        return EPISODE_STEPS.get(self.env.maze, CUSTOM_EPISODE_STEPS)

    def check(self, task: TaskParams, params: Params) -> None:
        """Episodes at least one plan long; the paper's selection rule only where it has thresholds."""
        where = f"task.{task.name}"
        h = task.diffusion.horizon
        if self.episode_steps < h:
            if self.env.episode_steps is not None:
                raise ConfigError(
                    f"{where}.env.episode_steps: {self.episode_steps} is shorter than diffusion.horizon={h}"
                )
            raise ConfigError(
                f"{where}.env.episode_steps: null means the maze {self.maze_name} protocol's {self.episode_steps} "
                f"steps, shorter than diffusion.horizon={h}; set env.episode_steps >= {h}"
            )
        if params.evolve != task.name:
            return
        paper_ok = self.env.layout is None and self.env.maze in PAPER_RULE_MAZES
        for phase in params.phases:
            if phase.discriminate.rule == "paper" and not paper_ok:
                raise ConfigError(
                    f"phases.{phase.name}.discriminate.rule: the rule 'paper' has thresholds for umaze, medium and "
                    f"large only ({task.name} is not one); set evolution.discriminate.rule to quantile or top_k"
                )


TASK_PARAMS = Maze2DTaskParams
