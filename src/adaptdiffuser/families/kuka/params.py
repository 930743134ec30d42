"""The settings of a KUKA task (``task.<name>`` with ``family: kuka``): the scene, position control and suction, the
scripted stacking demonstrator, and the two evaluations (stacking, seen; pick-and-place, unseen). Light to import
(no PyBullet)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from adaptdiffuser.config.errors import ConfigError

if TYPE_CHECKING:
    from adaptdiffuser.config.params import Params
    from adaptdiffuser.config.tasks import TaskParams

#: task names of the family: the model learns stacking; pick-and-place is evaluated beside it
TASK_NAMES = ("kuka-stacking",)
Frozen = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


class SceneSettings(BaseModel):
    """Where episodes start."""

    model_config = Frozen

    #: blocks are placed at random in this ring around the arm's base (metres)
    radius: Annotated[list[Annotated[float, Field(gt=0)]], Field(min_length=2, max_length=2)] = [0.35, 0.6]
    #: smallest distance between two blocks' centres at the start (0.2 x 0.2 blocks: >= 0.29 never overlap)
    min_gap: float = Field(0.3, ge=0)
    #: the arm starts at its home configuration + U(-noise, noise) per joint (radians)
    home_noise: float = Field(0.05, ge=0)
    #: pick-and-place starts keep the blocks at x <= this, away from the targets at x = 0.5
    pick_place_max_x: float = 0.1

    @field_validator("radius")
    @classmethod
    def _ring(cls, radius: list[float]) -> list[float]:
        if radius[0] >= radius[1]:
            raise ValueError(f"radius must be [inner, outer] with inner < outer, got {radius}")
        return radius


class ControlSettings(BaseModel):
    """How a planned configuration is executed."""

    model_config = Frozen

    #: physics steps (1/240 s each) per plan step (the reference: 10-20)
    substeps: int = Field(10, gt=0)
    position_gain: float = Field(0.3, gt=0)
    joint_force: float = Field(300.0, gt=0)
    #: the cup takes a block only when the block's top is within this distance of it (metres)
    suction_reach: float = Field(0.1, gt=0)
    #: the cup cannot take a block with another block on it (its top is covered)
    free_top_only: bool = False
    #: the most a joint's target may move from its current angle in one plan step (radians; None: no limit). The
    #: real iiwa turns its joints at 1.3-2.4 rad/s; 0.1 rad a step is 2.4 rad/s at 10 substeps. Without it a plan
    #: far from the data swings the arm at over 20 rad/s and flings the blocks it meets (docs/kuka.md)
    max_joint_step: float | None = Field(None, gt=0)


class DemonstratorSettings(BaseModel):
    """The scripted stacking demonstrator (the seen task's expert data)."""

    model_config = Frozen

    #: cup travel per plan step (metres); 0.04 = about 1 m/s at 10 substeps
    speed: float = Field(0.04, gt=0)
    #: carrying height of the cup (metres), raised above a growing tower
    safe_height: float = Field(0.35, gt=0)
    #: plan steps waited after attaching and after releasing
    dwell: int = Field(4, ge=0)
    #: plan steps recorded at rest after the last block, so plans learn to stay
    rest_steps: int = Field(20, ge=0)
    #: the tower's order, bottom to top: ``shuffled``, a random order per demonstration (the reference's data:
    #: every block is picked up in some demonstration); ``in_turn``, blocks 1, 2, 3 onto block 0 always (block 0
    #: never moves in the data, so a planner trained on it cannot move block 0 in pick-and-place)
    order: Literal["shuffled", "in_turn"] = "shuffled"


class PlanningSettings(BaseModel):
    """How plans are drawn and followed (stacking, pick-and-place and generation alike)."""

    model_config = Frozen

    #: keep each block's planned pose at its real one (the plan's first state) until the plan first turns that
    #: block's suction flag on, at every denoising step: the plan cannot move a block it has not picked up
    pin_resting_blocks: bool = False
    #: plan again after this many executed steps (null: after horizon - 1, the whole plan); the episode keeps its
    #: length, and pick-and-place still guides over stretches of horizon - 1 steps (``pick_place.next_block``)
    replan_every: int | None = Field(None, gt=0)
    #: execute by the blocks instead of the planned joints while the plan holds a block (its flag on): the cup is
    #: sent by inverse kinematics to the real block's top until it holds it, then carries it where the plan carries
    #: it; steps that hold nothing follow the planned joints. The plan says where blocks go, the scene where they are
    follow_blocks: bool = False


class CollectSettings(BaseModel):
    model_config = Frozen

    episodes: int = Field(300, gt=0)
    seed: int = Field(0, ge=0)


class PickPlaceSettings(BaseModel):
    """The unseen task: block i to target (0.5, y_i) with y = -0.8, -0.3, 0.3, 0.8, no demonstrations; the planner is
    guided toward the target of one block per replan."""

    model_config = Frozen

    #: the paper's setups: 1 = blocks scattered on the floor, 2 = blocks start in one tower
    setups: list[Literal[1, 2]] = Field(default_factory=lambda: [1, 2], min_length=1)
    #: plans per episode (the reference: 4, one block each)
    replans: int = Field(4, gt=0)
    episodes: int = Field(20, gt=0)
    seed: int = Field(3000, ge=0)
    #: the guidance pulls the chosen block over plan steps from this fraction of the horizon on (reference: half)
    guide_from: float = Field(0.5, ge=0, lt=1)
    #: which block a plan moves: ``in_turn``, block k mod 4 over the k-th stretch of horizon - 1 steps (one block
    #: per plan in a fixed order; the reference draws the order at random); ``free``, decided at each plan from the
    #: real scene: the block the cup holds, else the lowest-numbered one off its target with no block on it (a
    #: tower is taken from the top, which a cup with ``control.free_top_only`` needs in setup 2)
    next_block: Literal["in_turn", "free"] = "in_turn"
    #: where the guidance acts: ``mean``, each denoising step's mean scaled by its variance (the paper's Eq. 5);
    #: ``x0``, the denoiser's clean estimate at every step (``alpha`` then means a much smaller pull per step)
    guide_on: Literal["mean", "x0"] = "mean"
    #: condition each plan on picking the guided block: its suction flag on and the other blocks' off over the plan
    #: steps between these two fractions of the horizon, every flag off after (inpainted, as the start is); null: no
    #: condition (the paper: guidance alone, which seldom makes the plan pick the guided block, docs/kuka.md)
    hold: Annotated[list[Annotated[float, Field(ge=0, le=1)]], Field(min_length=2, max_length=2)] | None = None
    #: condition each plan's last state on the scene it should leave: the plan's start state (arm, flags, every
    #: block) with the guided block's xy at its target, inpainted as the start is (the reference's pick-and-place
    #: code sets its plans' last state so); false: the plan's end is free (guidance alone)
    goal_state: bool = False
    batch_size: int = Field(20, gt=0)

    @field_validator("hold")
    @classmethod
    def _span(cls, hold: list[float] | None) -> list[float] | None:
        if hold is not None and hold[0] >= hold[1]:
            raise ValueError(f"hold must be [from, to] fractions of the horizon with from < to, got {hold}")
        return hold

    def hold_steps(self, horizon: int) -> tuple[int, int] | None:
        """The plan steps ``hold`` covers in a ``horizon``-step plan: from ``first`` to before ``last``, never step 0
        (the real start); None without a hold."""
        if self.hold is None:
            return None
        first, last = (max(1, int(f * horizon)) for f in self.hold)
        return first, last


class SelectionSettings(BaseModel):
    """What the discriminator asks of an executed pick-and-place episode besides tracking (our addition)."""

    model_config = Frozen

    #: reject an episode whose executed states leave the stacking data's range of some dimension by more than this
    #: fraction of that range (a block tipped over or flung away: states the min-max model cannot plan, which
    #: dominated fine-tuning's loss without this check, docs/kuka.md); null: no check (the reference)
    max_range_excess: float | None = Field(0.25, ge=0)


class KukaTaskParams(BaseModel):
    """The KUKA iiwa arm with a suction cup and four blocks on PyBullet: ``kuka-stacking``."""

    model_config = Frozen
    OPTIONAL_STAGES: ClassVar[tuple[str, ...]] = ("evolve",)
    #: the family's unseen task: its evaluate-unseen stages run, its settings are the section of this name
    UNSEEN_TASK: ClassVar[str] = "pick_place"

    family: Literal["kuka"] = "kuka"
    scene: SceneSettings = Field(default_factory=SceneSettings)
    control: ControlSettings = Field(default_factory=ControlSettings)
    demonstrator: DemonstratorSettings = Field(default_factory=DemonstratorSettings)
    collect: CollectSettings = Field(default_factory=CollectSettings)
    #: stacking episodes: this many open-loop plans of the horizon, each from where the last one ended
    replans: int = Field(3, gt=0)
    planning: PlanningSettings = Field(default_factory=PlanningSettings)
    pick_place: PickPlaceSettings = Field(default_factory=PickPlaceSettings)
    selection: SelectionSettings = Field(default_factory=SelectionSettings)

    def describe_data(self) -> str:
        """The collect stage's recipe, one line (``adaptdiffuser check``)."""
        return f"{self.collect.episodes} scripted stacking demonstrations (seed {self.collect.seed})"

    def describe_unseen(self) -> str:
        """The unseen task's evaluation, one line (``adaptdiffuser check``)."""
        p = self.pick_place
        return f"pick-and-place, {p.episodes} episodes in each of setups {p.setups}"

    def tiny(self, task: TaskParams[KukaTaskParams]) -> dict[str, Any]:
        """This family's keys at tiny scale (``adaptdiffuser profile NAME --tiny``): two demonstrations, one
        pick-and-place episode per setup."""
        return {"collect": {"episodes": 2}, "pick_place": {"episodes": 1, "batch_size": 1}}

    def check_name(self, name: str) -> None:
        if name not in TASK_NAMES:
            raise ConfigError(f"task.{name}: KUKA tasks are named {list(TASK_NAMES)}")

    def check(self, task: TaskParams[KukaTaskParams], params: Params) -> None:
        """Plans at least two steps long, a hold span that holds some step of them, replans within a plan."""
        if task.diffusion.horizon < 2:
            raise ConfigError(f"task.{task.name}.diffusion.horizon: KUKA plans need at least 2 steps")
        horizon = task.diffusion.horizon
        steps = self.pick_place.hold_steps(horizon)
        if steps is not None and steps[0] >= steps[1]:
            raise ConfigError(
                f"task.{task.name}.pick_place.hold: {self.pick_place.hold} of a {horizon}-step plan holds no step "
                f"(from step {steps[0]} to before step {steps[1]}); widen the span"
            )
        every = self.planning.replan_every
        if every is not None and every > horizon - 1:
            raise ConfigError(
                f"task.{task.name}.planning.replan_every: {every} steps is more than a plan holds "
                f"(horizon - 1 = {horizon - 1})"
            )


TASK_PARAMS = KukaTaskParams
