"""Settings of the value network that guides Diffuser's locomotion planner (a section of a locomotion task).

Kept apart from :mod:`adaptdiffuser.value_training` so that reading params never imports the training code.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class ValueSettings(BaseModel):
    """Value training settings (defaults: Diffuser's locomotion value config)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    steps: int = Field(200_000, gt=0)
    batch_size: int = Field(32, gt=0)
    lr: float = Field(2e-4, gt=0)
    seed: int = Field(0, ge=0)
    discount: float = Field(0.997, gt=0, le=1)
    terminal_penalty: float = -100.0
    log_every: int = Field(1000, gt=0)
    #: steps between resume states (and one at the end), so that a killed value training goes on from there
    checkpoint_every: int = Field(5000, gt=0)
    #: share of the episodes kept out of value training; the value's R^2 on their windows is the stage's metric
    #: ``value_heldout_r2`` (0: train on every episode, no R^2)
    holdout_fraction: float = Field(0.1, ge=0.0, lt=1.0)
