"""Value network for Diffuser's locomotion guidance: the temporal U-Net's down path, then an MLP to one scalar."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from adaptdiffuser.models.unet import Mish, ResidualTemporalBlock, down_path, time_embedding


def _halve(length: int) -> int:
    """The length after a stride-2, padding-1, kernel-3 convolution."""
    return (length + 1) // 2


def _norm_channels(c: int) -> int:
    """``c`` rounded down to a multiple of 8 (GroupNorm(8) needs it), at least 8."""
    return max(8, c // 8 * 8)


class ValueNetwork(nn.Module):
    """Predicts the value of a noisy trajectory: ``(x [batch, horizon, transition_dim], t [batch]) -> [batch]``.

    As Diffuser's ``ValueFunction``: down blocks of the temporal U-Net (two residual temporal blocks per level,
    stride-2 downsampling between levels), two more residual blocks that halve the channels with downsampling,
    then the flattened features and the step embedding go through an MLP. Any horizon works (lengths round up
    when halved), but the network is built for one fixed ``horizon``.
    """

    def __init__(
        self,
        transition_dim: int,
        horizon: int,
        dim: int = 32,
        dim_mults: tuple[int, ...] = (1, 2, 4, 8),
        kernel_size: int = 5,
    ) -> None:
        super().__init__()
        if horizon <= 0 or transition_dim <= 0 or not dim_mults:
            raise ValueError("value network needs a positive horizon and transition_dim and some dim_mults")
        self.transition_dim = transition_dim
        self.horizon = horizon
        self.dim = dim
        self.dim_mults = tuple(dim_mults)
        self.kernel_size = kernel_size
        dims = [transition_dim, *(dim * m for m in dim_mults)]
        self.time_mlp = time_embedding(dim)
        self.down = down_path(dims, dim, kernel_size)
        length = horizon
        for _ in range(len(dims) - 2):
            length = _halve(length)
        mid, mid2, mid3 = dims[-1], _norm_channels(dims[-1] // 2), _norm_channels(dims[-1] // 4)
        self.mid1 = ResidualTemporalBlock(mid, mid2, dim, kernel_size)
        self.mid_down1 = nn.Conv1d(mid2, mid2, 3, stride=2, padding=1)
        self.mid2 = ResidualTemporalBlock(mid2, mid3, dim, kernel_size)
        self.mid_down2 = nn.Conv1d(mid3, mid3, 3, stride=2, padding=1)
        fc_dim = mid3 * _halve(_halve(length))
        hidden = max(fc_dim // 2, dim)
        self.head = nn.Sequential(nn.Linear(fc_dim + dim, hidden), Mish(), nn.Linear(hidden, 1))

    def config(self) -> dict[str, Any]:
        """The constructor arguments, JSON-able, to rebuild this network."""
        return {
            "transition_dim": self.transition_dim,
            "horizon": self.horizon,
            "dim": self.dim,
            "dim_mults": list(self.dim_mults),
            "kernel_size": self.kernel_size,
        }

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """``x``: ``[batch, horizon, transition_dim]``; ``t``: ``[batch]`` diffusion steps; returns ``[batch]``."""
        if x.shape[1:] != (self.horizon, self.transition_dim):
            raise ValueError(
                f"value network expects trajectories [batch, {self.horizon}, {self.transition_dim}], "
                f"got {tuple(x.shape)}"
            )
        h = x.transpose(1, 2)
        emb = self.time_mlp(t)
        for block1, block2, downsample in self.down:
            h = downsample(block2(block1(h, emb), emb))
        h = self.mid_down1(self.mid1(h, emb))
        h = self.mid_down2(self.mid2(h, emb))
        return self.head(torch.cat([h.flatten(1), emb], dim=-1)).squeeze(-1)
