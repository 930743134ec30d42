"""The settings of a Maze2D task (``task.<name>`` with ``family: maze2d`` in params.yaml)."""

from __future__ import annotations

from dataclasses import field
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal

from pydantic import ValidationInfo, field_validator
from pydantic.dataclasses import dataclass

from adaptdiffuser.config.errors import ConfigError
from adaptdiffuser.config.fields import (
    HALF_CELL,
    UNIT,
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
    from adaptdiffuser.config.phases import PhaseParams
    from adaptdiffuser.config.tasks import TaskParams

PAPER_RULE_MAZES = ("umaze", "medium", "large")
#: how an evolution phase makes its synthetic data (``evolution.generate.recipe``; see :class:`EvolutionSettings`)
RECIPES = ("plans", "rollouts")
CUSTOM_EPISODE_STEPS = 300  # what the simulator uses for a custom layout when env.episode_steps is null


@dataclass(frozen=True, config=SECTION)
class EnvParams:
    #: a custom maze: list of strings, '#' wall, '.' free, 'G' evaluation goal (None: ``maze``)
    layout: list[Str] | None = None
    #: umaze | medium | large (ignored when layout is set)
    maze: Str = "umaze"
    #: None = the protocol's length for the maze (300 / 600 / 800)
    episode_steps: PositiveInt | None = None
    #: reward 1 at every step within this distance of the goal
    goal_radius: PositiveFloat = 0.5
    #: start = random free cell centre + U(-noise, noise)
    reset_pos_noise: NonNegativeFloat = 0.1
    #: start velocity ~ N(0, noise^2)
    reset_vel_noise: NonNegativeFloat = 0.1
    #: each episode draws a random goal cell (D4RL's "multi" variant)
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
    """D4RL's waypoint controller (the data and R_max)."""

    p_gain: PositiveFloat = 10.0
    d_gain: Float = 1.0
    #: non-final waypoints shifted by -U(0, jitter)
    jitter: NonNegativeFloat = 0.2
    #: move to the next waypoint within this distance
    waypoint_radius: PositiveFloat = 0.3


@dataclass(frozen=True, config=SECTION)
class CollectParams:
    #: expert steps (paper profiles: 1e6 U-Maze, 2e6 Medium, 4e6 Large)
    steps: PositiveInt = 200_000
    seed: Seed = 0


@dataclass(frozen=True, config=SECTION)
class GoldCoinParams:
    """The unseen task: reach the goal and pick up a coin on the way (no expert coin data)."""

    #: fixed evaluation cases per kind: coin on the path, off it, behind the start
    cases_per_kind: PositiveInt = 10
    seed: Seed = 2000
    #: the coin is picked when the agent passes within this distance
    radius: PositiveFloat = 0.5
    batch_size: PositiveInt = 50
    pictures: NonNegativeInt = 3


@dataclass(frozen=True, config=SECTION)
class EvolutionSettings:
    """The random tasks of a Maze2D task's evolution phases (``task.<name>.evolution``).

    The phase's recipe is generic (``evolution.generate.recipe``). ``plans`` (the default): one open-loop plan of
    the model's horizon per random (start, goal) task, tracked by the plan follower in the discriminator, the paper's
    rule applied with L = the horizon. ``rollouts`` (the author's recipe, official AdaptDiffuser repository, issue
    7): closed-loop rollouts in the simulator that replan every ``evolution.generate.replan_every`` steps (0: plan
    once) and end when the goal is reached or after the maze's episode length; the discriminator keeps those that
    reach the goal by the rule with L = the steps taken to reach it, and the kept rollouts are padded by staying at
    the goal for a horizon, so the model learns plans that reach it and stay. ``stay_at_goal`` does the same for
    the ``plans`` recipe's kept trajectories: cut where they first reach the goal and fill the rest of the horizon
    by staying there (off by default: the plans recipe as it always was).
    """

    stay_at_goal: Bool = False
    #: a task's start: its cell centre + U(-cell_spread, cell_spread)
    cell_spread: Annotated[Float, HALF_CELL] = 0.4
    #: share of each phase's tasks with a gold coin in a third random cell, planned with guidance ``alpha``
    coin_fraction: Annotated[Float, UNIT] = 0.25


@dataclass(frozen=True, config=SECTION)
class FollowerParams:
    """The plan follower (evaluation and the discriminator's tracking): action = ``p_gain`` (planned xy - xy) +
    ``d_gain`` (planned velocity - velocity), clipped (Diffuser uses 1 and 1)."""

    p_gain: PositiveFloat = 2.0
    d_gain: NonNegativeFloat = 0.5


@dataclass(frozen=True, config=SECTION)
class Maze2DTaskParams:
    """A Maze2D task: the maze and its protocol (``env``), the waypoint expert, data collection and the unseen
    gold-coin evaluation."""

    OPTIONAL_STAGES: ClassVar[tuple[str, ...]] = ("evolve",)
    #: how its evolution phases may make their data (``evolution.generate.recipe``)
    EVOLUTION_RECIPES: ClassVar[tuple[str, ...]] = RECIPES
    #: the family's unseen task: its evaluate-unseen stages run, its settings are the section of this name
    UNSEEN_TASK: ClassVar[str] = "gold_coin"

    family: Literal["maze2d"] = "maze2d"
    env: EnvParams = field(default_factory=EnvParams)
    expert: ExpertParams = field(default_factory=ExpertParams)
    collect: CollectParams = field(default_factory=CollectParams)
    gold_coin: GoldCoinParams = field(default_factory=GoldCoinParams)
    evolution: EvolutionSettings = field(default_factory=EvolutionSettings)
    follower: FollowerParams = field(default_factory=FollowerParams)

    def describe_data(self) -> str:
        """The collect stage's recipe, one line (``adaptdiffuser check``)."""
        return f"{self.collect.steps} expert steps (seed {self.collect.seed})"

    def describe_unseen(self) -> str:
        """The unseen task's evaluation, one line (``adaptdiffuser check``)."""
        return f"{self.gold_coin.cases_per_kind} gold-coin cases per kind"

    def tiny(self, task: TaskParams[Maze2DTaskParams]) -> dict[str, Any]:
        """This family's keys at tiny scale (``adaptdiffuser profile NAME --tiny``): expert data enough for a few
        episodes of one plan's length, one gold-coin case per kind."""
        return {
            "collect": {"steps": max(5000, 20 * task.diffusion.horizon)},
            "gold_coin": {"cases_per_kind": 1, "batch_size": 2, "pictures": 1},
        }

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

    def check(self, task: TaskParams[Maze2DTaskParams], params: Params) -> None:
        """Episodes at least one plan long; the paper's selection rule only where it has thresholds; rollouts
        replan within a plan's length and are judged as executed."""
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
            if phase.generate.recipe == "rollouts":
                self._check_rollouts(task, phase)

    @staticmethod
    def _check_rollouts(task: TaskParams[Maze2DTaskParams], phase: PhaseParams) -> None:
        where = f"phases.{phase.name}"
        h = task.diffusion.horizon
        if phase.generate.replan_every > h:
            raise ConfigError(
                f"{where}.generate.replan_every: {phase.generate.replan_every} exceeds diffusion.horizon={h} of "
                f"{task.name} (a plan's length); use 1..{h}, or 0 to plan once per rollout"
            )
        if not phase.discriminate.tracking:
            raise ConfigError(
                f"{where}.discriminate.tracking: {where}.generate.recipe is rollouts, which are executed in the "
                "simulator as they are made; tracking must be true (the no-simulator ablation needs recipe: plans)"
            )


TASK_PARAMS = Maze2DTaskParams
