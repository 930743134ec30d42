"""Conditioning by inpainting: overwrite the observation part of chosen time steps with known states."""

from __future__ import annotations

from collections.abc import Callable

import torch

Conditions = dict[int, torch.Tensor]
#: a family's own constraint on plans, applied after the inpainting at every denoising step: normalized trajectories
#: ``[batch, horizon, transition]`` in, the same shape out (e.g. KUKA's blocks kept where they rest)
Projection = Callable[[torch.Tensor], torch.Tensor]


def apply_inpainting(x: torch.Tensor, conditions: Conditions, act_dim: int) -> torch.Tensor:
    """Return ``x`` with ``x[:, t, act_dim:] = state`` for each ``t: state`` (``state`` is ``[batch, obs]``)."""
    if not conditions:
        return x
    x = x.clone()
    for t, state in conditions.items():
        x[:, t, act_dim:] = state
    return x


def start_conditions(x0: torch.Tensor, act_dim: int) -> Conditions:
    """Plans start at the current state (locomotion: Diffuser's value-guided planner)."""
    return {0: x0[:, 0, act_dim:]}


def start_goal_conditions(x0: torch.Tensor, act_dim: int) -> Conditions:
    """Plans start at the current state and end at the goal state (navigation by inpainting)."""
    return {0: x0[:, 0, act_dim:], x0.shape[1] - 1: x0[:, -1, act_dim:]}


#: conditioning by name (stored in a model bundle's config): the conditions of clean training windows
CONDITIONINGS: dict[str, Callable[[torch.Tensor, int], Conditions]] = {
    "start": start_conditions,
    "start_goal": start_goal_conditions,
}


def training_conditions(kind: str, x0: torch.Tensor, act_dim: int) -> Conditions:
    """The inpainting conditions of training windows ``x0`` for the conditioning named ``kind``."""
    if kind not in CONDITIONINGS:
        raise ValueError(f"unknown conditioning {kind!r}; known: {sorted(CONDITIONINGS)}")
    return CONDITIONINGS[kind](x0, act_dim)
