"""One pydantic model per ``params.yaml`` section: types, defaults and the checks a single field can make.

The models are frozen pydantic dataclasses with unknown keys forbidden, so ``dataclasses.asdict`` and
``dataclasses.replace`` keep working (``replace`` validates the new values).
"""

from __future__ import annotations

from dataclasses import field
from typing import Annotated

from pydantic import ConfigDict
from pydantic.dataclasses import dataclass

from adaptdiffuser.config.fields import (
    FRACTION,
    ODD,
    UNIT,
    UNIT_OPEN,
    Bool,
    Float,
    Int,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    Sampler,
    Seed,
    Str,
    one_of,
    requires,
)

SECTION = ConfigDict(extra="forbid")
SELECTION_RULES = ("paper", "quantile", "top_k")
LR_SCHEDULES = ("constant", "cosine")

DimMults = Annotated[
    list[Int], requires(lambda v: len(v) > 0 and all(m > 0 for m in v), "a non-empty list of positive integers")
]


@dataclass(frozen=True, config=SECTION)
class ModelParams:
    #: the temporal U-Net's base width (paper: 32, 3.68 M parameters; 16: 0.92 M, ~2x faster on CPU)
    dim: PositiveInt = 16
    dim_mults: DimMults = field(default_factory=lambda: [1, 4, 8])
    kernel_size: Annotated[PositiveInt, ODD] = 5


@dataclass(frozen=True, config=SECTION)
class CompileParams:
    """Run the U-Net under ``torch.compile`` (inductor) when training and when sampling: the same function within
    float rounding, faster once compiled (docs/speed.md), at a compile cost paid once per process."""

    training: Bool = False
    sampling: Bool = False


@dataclass(frozen=True, config=SECTION)
class DiffusionParams:
    #: plan length; divisible by 2^(len(model.dim_mults) - 1)
    horizon: PositiveInt = 128
    n_steps: PositiveInt = 64
    #: false: the network predicts x0 (Diffuser's Maze2D setting)
    predict_epsilon: Bool = False
    clip_denoised: Bool = True
    action_weight: PositiveFloat = 1.0
    loss_discount: PositiveFloat = 1.0


@dataclass(frozen=True, config=SECTION)
class PretrainParams:
    steps: PositiveInt = 8000
    batch_size: PositiveInt = 32
    #: batches per optimizer step (paper: 2)
    grad_accum: PositiveInt = 1
    lr: PositiveFloat = 2e-4
    lr_schedule: Annotated[Str, one_of(*LR_SCHEDULES)] = "constant"  # constant (Diffuser) | cosine (to 0 at the end)
    lr_warmup: NonNegativeInt = 0  # steps of linear warm-up from lr / lr_warmup to lr
    ema_decay: Annotated[Float, UNIT_OPEN] = 0.995
    ema_every: PositiveInt = 10
    #: steps before the EMA starts following the weights (paper: 2000)
    ema_start: NonNegativeInt = 500
    log_every: PositiveInt = 100
    #: steps between resume points, should the stage be killed
    checkpoint_every: PositiveInt = 1000
    seed: Seed = 0
    #: share of expert episodes the models train on (paper ablation: 0.2, 0.5, 1.0)
    expert_fraction: Annotated[Float, FRACTION] = 1.0


@dataclass(frozen=True, config=SECTION)
class PlannerParams:
    #: ddim (strided, deterministic; sampler_steps of them) | ddpm (the full chain); replan_every: 0 = plan once at
    #: t = 0 (Diffuser's protocol), > 0 = replan every that many steps
    sampler: Sampler = "ddim"
    sampler_steps: PositiveInt = 16
    replan_every: NonNegativeInt = 0


@dataclass(frozen=True, config=SECTION)
class EvaluateParams:
    episodes: PositiveInt = 50
    #: training seed s plays the start states of seed + s: each seed its own episodes, shared by its phases and
    #: controls (paired)
    seed: Seed = 1000
    #: the held-out start states (held_out_seed + s): fresh draws from the task's start distribution (not new
    #: situations), reported beside the main ones and never used to choose anything (sweep trials play
    #: sweep.evaluate_seed and sweep.held_out_seed instead); 0 held-out episodes: none
    held_out_seed: Seed = 7000
    held_out_episodes: NonNegativeInt = 50
    #: episodes planned together in one batch
    batch_size: PositiveInt = 50
    pictures: NonNegativeInt = 4


@dataclass(frozen=True, config=SECTION)
class GenerateParams:
    #: plans per phase, for random tasks the family samples, from phase k-1's model
    tasks: PositiveInt = 1024
    batch_size: PositiveInt = 128
    #: phase k uses a seed derived from (seed, k)
    seed: Seed = 100
    sampler: Sampler = "ddim"
    sampler_steps: PositiveInt = 16  # and <= diffusion.n_steps (checked on Params)
    #: how a phase makes its data: ``plans`` (the model's plans, executed by the discriminator) or another recipe
    #: of the evolved task's family (its ``EVOLUTION_RECIPES``; Maze2D: ``rollouts``). Here, not in the task's
    #: entry, so that changing it reruns the phases only, never phase 0 or phase 1's control.
    recipe: Str = "plans"
    replan_every: NonNegativeInt = 32  # recipes that run the planner closed loop: replan every this many steps


@dataclass(frozen=True, config=SECTION)
class DiscriminateParams:
    #: false = ablation: no simulator, select raw plans by their planned reward
    tracking: Bool = True
    #: reject a plan when tracking ever leaves it by more than this (maze cells)
    max_error: PositiveFloat = 1.0
    #: paper (appendix reward/length thresholds) | quantile | top_k, on real reward
    rule: Annotated[Str, one_of(*SELECTION_RULES)] = "paper"
    #: rule quantile: keep returns at or above this quantile of those that track
    quantile: Annotated[Float, UNIT] = 0.5
    #: rule top_k: keep this many best returns
    top_k: PositiveInt = 64


@dataclass(frozen=True, config=SECTION)
class FinetuneParams:
    #: fine-tuning steps, as a fraction of pretrain.steps (the paper: a quarter)
    steps_fraction: PositiveFloat = 0.25
    #: expert share of each batch; the rest is split evenly over phases 1..k's data
    expert_weight: Annotated[Float, UNIT_OPEN] = 0.5
    seed: Seed = 1
    optimizer: Annotated[Str, one_of("restart", "carry")] = "restart"  # Adam: fresh, or phase k-1's carried on


@dataclass(frozen=True, config=SECTION)
class EvolutionParams:
    """The defaults of every evolution phase; ``phases.<name>`` entries override any of these keys."""

    generate: GenerateParams = field(default_factory=GenerateParams)
    discriminate: DiscriminateParams = field(default_factory=DiscriminateParams)
    finetune: FinetuneParams = field(default_factory=FinetuneParams)
