"""Conditioning by inpainting: overwrite the observation part of chosen time steps with known states."""

from __future__ import annotations

import torch

Conditions = dict[int, torch.Tensor]


def apply_inpainting(x: torch.Tensor, conditions: Conditions, act_dim: int) -> torch.Tensor:
    """Return ``x`` with ``x[:, t, act_dim:] = state`` for each ``t: state`` (``state`` is ``[batch, obs]``)."""
    if not conditions:
        return x
    x = x.clone()
    for t, state in conditions.items():
        x[:, t, act_dim:] = state
    return x
