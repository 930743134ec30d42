"""The settings of a locomotion task (``task.<name>`` with ``family: locomotion``): the behaviour policy and dataset
recipe, the value function and the value-guided planner. Light to import (no simulator, no stable-baselines3)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from adaptdiffuser.config.errors import ConfigError
from adaptdiffuser.config.value_settings import ValueSettings

if TYPE_CHECKING:
    from adaptdiffuser.config.params import Params
    from adaptdiffuser.config.tasks import TaskParams

Algorithm = Literal["sac", "td3", "ppo"]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
ENV_IDS: dict[str, str] = {"hopper": "Hopper-v5", "walker2d": "Walker2d-v5", "halfcheetah": "HalfCheetah-v5"}
#: dataset kinds of a task name (``hopper-medium-replay`` -> ``medium-replay``)
DATASET_KINDS: tuple[str, ...] = ("medium", "medium-replay", "medium-expert")

#: the paper's reward-discriminator thresholds (appendix table; phase 1, phase 2), on a 1000-step return scale
PAPER_THRESHOLDS: dict[str, tuple[float, float]] = {
    "halfcheetah-medium-expert": (10840, 10867),
    "hopper-medium-expert": (3639, 3681),
    "walker2d-medium-expert": (4900, 4950),
    "halfcheetah-medium": (5005, 5150),
    "hopper-medium": (3211, 3225),
    "walker2d-medium": (3700, 3843),
    "halfcheetah-medium-replay": (4600, 4800),
    "hopper-medium-replay": (3100, 3136),
    "walker2d-medium-replay": (3900, 3920),
}


def parse_task_name(name: str) -> tuple[str, str]:
    """``hopper-medium-replay`` -> ``("Hopper-v5", "medium-replay")``; ``ValueError`` for an unknown name."""
    robot, _, kind = name.partition("-")
    if robot not in ENV_IDS or kind not in DATASET_KINDS:
        raise ValueError(
            f"unknown locomotion task {name!r}: expected '<robot>-<dataset>' with robot in {sorted(ENV_IDS)} "
            f"and dataset in {list(DATASET_KINDS)} (e.g. 'hopper-medium-replay')"
        )
    return ENV_IDS[robot], kind


class BehaviourSettings(BaseModel):
    """Every knob of behaviour training and dataset recording."""

    model_config = ConfigDict(extra="forbid")

    #: stable-baselines3 algorithm; PPO reached Hopper's medium target fastest in wall-clock on 2 CPU cores
    #: (~2100 steps/s, 33 after ~100k steps in under a minute; SAC and TD3 had not after 50-60k steps / 13 min)
    algorithm: Algorithm = "ppo"
    seed: int = Field(0, ge=0)
    #: normalized score the ``medium`` policy aims at: the centre of its band
    medium_score: FiniteFloat = 33.0
    #: half-width of the band the ``medium`` policy's score must lie in: ``medium_score +- medium_band``, measured
    #: as the dataset is recorded (with ``rollout_noise``) on ``band_episodes`` episodes; training that jumps over
    #: the band goes back to its last checkpoint below it and evaluates more often. ``None``: no band (stop at the
    #: first evaluation at or above ``medium_score``, or at the budget's end; for tiny test budgets only)
    medium_band: FiniteFloat | None = Field(3.0, gt=0.0)
    #: episodes of that measurement; the score must lie inside the band by one standard error of its mean. A
    #: policy that passes records the ``medium`` dataset (``dataset_steps``) and is chosen only when the dataset's
    #: episodes pass too: the dataset's score is what the band states
    band_episodes: int = Field(50, gt=1)
    #: the shortest interval between evaluations when going back (rounded up to whole PPO rollouts)
    min_eval_every: int = Field(2_048, gt=0)
    #: normalized score the ``expert`` policy (``medium-expert`` only) trains on to
    expert_score: FiniteFloat = 90.0
    #: environment steps budget for the medium policy (all steps trained, paths gone back from included; without a
    #: band, the policy at the budget's end is saved, reached or not). PPO on Walker2d needed 919 552 on one of three
    #: variations (docs/locomotion.md); Hopper's profiles state their own 600 000
    max_train_steps: int = Field(1_000_000, gt=0)
    #: total environment steps budget to reach ``expert_score``
    max_expert_steps: int = Field(1_000_000, gt=0)
    #: uniformly random steps before the off-policy learners start (SAC, TD3)
    learning_starts: int = Field(5_000, ge=0)
    #: environment steps between evaluations (PPO rounds each chunk up to whole rollouts of ``ppo_n_steps``)
    eval_every: int = Field(20_480, gt=0)
    eval_episodes: int = Field(5, gt=0)
    eval_seed: int = Field(1_000_000, ge=0)
    #: steps of each recorded dataset part (D4RL: 1M for medium; medium-expert has 2 parts)
    dataset_steps: int = Field(1_000_000, gt=0)
    #: Gaussian action noise of the recorded rollouts, as a fraction of the action half-range
    rollout_noise: FiniteFloat = Field(0.1, ge=0.0)
    episode_steps: int = Field(1_000, gt=0)
    #: torch intra-op threads while training and recording
    torch_threads: int = Field(2, gt=0)
    #: hidden layer sizes of the actor and critic networks
    net_arch: list[Annotated[int, Field(gt=0)]] = Field(default_factory=lambda: [256, 256], min_length=1)
    learning_rate: FiniteFloat = Field(3e-4, gt=0.0)
    batch_size: int = Field(256, gt=0)
    #: PPO rollout length per update
    ppo_n_steps: int = Field(2_048, gt=1)

    @model_validator(mode="after")
    def _check_targets(self) -> BehaviourSettings:
        if self.expert_score < self.medium_score:
            raise ValueError(f"expert_score ({self.expert_score}) must be >= medium_score ({self.medium_score})")
        if self.max_expert_steps < self.max_train_steps:
            raise ValueError(
                f"max_expert_steps ({self.max_expert_steps}) must be >= max_train_steps ({self.max_train_steps})"
            )
        return self


class PlannerSettings(BaseModel):
    """Diffuser's value-guided locomotion planner (defaults: its locomotion config)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    #: plans sampled per decision; the first action of the highest-value one is executed
    n_samples: int = Field(64, gt=0)
    #: guidance scale of the value gradient
    scale: float = Field(0.1, ge=0)
    n_guide_steps: int = Field(2, ge=0)
    #: diffusion steps below this one are not guided
    t_stopgrad: int = Field(2, ge=0)
    scale_grad_by_std: bool = True
    #: replan from the last executed plan shifted by one step and noised to this diffusion step (fewer network
    #: calls per decision); ``None``: every decision from pure noise (Diffuser)
    warm_start_step: int | None = Field(None, ge=0)


class EvolutionSettings(BaseModel):
    """Where a locomotion task's evolution phases start their generated segments."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    #: share of generated segments starting from a fresh reset; the rest start from dataset states (qpos, qvel)
    reset_fraction: float = Field(0.5, ge=0.0, le=1.0)


class LocomotionTaskParams(BaseModel):
    """A locomotion task named ``<robot>-<dataset>`` (``hopper-medium``, ``walker2d-medium-replay``...)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)
    OPTIONAL_STAGES: ClassVar[tuple[str, ...]] = ("evolve",)

    family: Literal["locomotion"] = "locomotion"
    #: evaluation episodes end after this many steps or on termination (D4RL: 1000)
    episode_steps: int = Field(1000, gt=0)
    behaviour: BehaviourSettings = Field(default_factory=BehaviourSettings)
    value: ValueSettings = Field(default_factory=ValueSettings)
    value_model: ValueModelSettings = Field(default_factory=lambda: ValueModelSettings())
    guide: PlannerSettings = Field(default_factory=PlannerSettings)
    evolution: EvolutionSettings = Field(default_factory=EvolutionSettings)

    def describe_data(self) -> str:
        """The collect stage's recipe, one line (``adaptdiffuser check``)."""
        b = self.behaviour
        return f"{b.algorithm} behaviour policy to score {b.medium_score:g}, {b.dataset_steps} dataset steps per part"

    def tiny(self, task: TaskParams[LocomotionTaskParams]) -> dict[str, Any]:
        """This family's keys at tiny scale (``adaptdiffuser profile NAME --tiny``): a few PPO updates with no
        score band, a few hundred dataset steps, two value steps, two samples per decision guided once, episodes
        one plan long."""
        return {
            "episode_steps": task.diffusion.horizon,
            "behaviour": {
                "max_train_steps": 1024,
                "max_expert_steps": 1536,
                "ppo_n_steps": 256,
                "batch_size": 64,
                "eval_every": 512,
                "eval_episodes": 1,
                "dataset_steps": 1000,
                "episode_steps": 200,
                "torch_threads": 1,
                "medium_band": None,
                "learning_starts": 100,
            },
            "value": {"steps": 2, "batch_size": 4, "log_every": 1},
            "guide": {"n_samples": 2, "n_guide_steps": 1},
        }

    def check_name(self, name: str) -> None:
        """The name says the robot and the dataset, like ``walker2d-medium-replay``."""
        try:
            parse_task_name(name)
        except ValueError as err:
            raise ConfigError(f"task.{name}: {err}") from None

    def check(self, task: TaskParams[LocomotionTaskParams], params: Params) -> None:
        """Episodes at least one plan long; a warm start within the diffusion chain."""
        where = f"task.{task.name}"
        h = task.diffusion.horizon
        if self.episode_steps < h:
            raise ConfigError(f"{where}.episode_steps: {self.episode_steps} is shorter than diffusion.horizon={h}")
        warm, n_steps = self.guide.warm_start_step, task.diffusion.n_steps
        if warm is not None and warm >= n_steps:
            raise ConfigError(
                f"{where}.guide.warm_start_step: {warm} is not a diffusion step (0..{n_steps - 1}, diffusion.n_steps)"
            )
        if params.evolve != task.name:
            return
        for phase in params.phases:
            d = phase.discriminate
            if not d.tracking:
                raise ConfigError(
                    f"phases.{phase.name}.discriminate.tracking: locomotion segments are judged by executing them; "
                    "it must be true"
                )
            if d.rule == "paper" and task.name not in PAPER_THRESHOLDS:
                raise ConfigError(
                    f"phases.{phase.name}.discriminate.rule: the paper has no threshold for {task.name}; "
                    "use quantile or top_k"
                )


class ValueModelSettings(BaseModel):
    """The value network: the U-Net's down path (its own widths) and an MLP head."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    dim: int = Field(32, gt=0)
    dim_mults: list[Annotated[int, Field(gt=0)]] = Field(default_factory=lambda: [1, 2, 4, 8], min_length=1)


LocomotionTaskParams.model_rebuild()
TASK_PARAMS = LocomotionTaskParams
