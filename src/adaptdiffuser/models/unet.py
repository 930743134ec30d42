"""Temporal U-Net over trajectories ``[batch, horizon, transition_dim]`` (Diffuser's architecture)."""

from __future__ import annotations

import math

import torch
from torch import nn


class SinusoidalEmbedding(nn.Module):
    """Sinusoidal embedding of the diffusion step, computed in float32 and returned in the module's floating-point
    type (an empty buffer follows ``.to(dtype)``; float32 unless a caller converts the network, e.g. to float64)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim
        self.register_buffer("dtype_of", torch.zeros(0), persistent=False)

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        freqs = torch.exp(-math.log(10000) * torch.arange(half, device=t.device) / max(half - 1, 1))
        angles = t.float()[:, None] * freqs[None, :]
        return torch.cat([angles.sin(), angles.cos()], dim=-1).to(self.dtype_of.dtype)


class Mish(nn.Module):
    """Mish, ``x tanh(softplus(x))``: aten's kernel when run eagerly; under ``torch.compile`` the equal one-``exp``
    form ``x n (n + 2) / (n (n + 2) + 2)`` with ``n = exp(x)``, which inductor fuses with the GroupNorm before it
    into one vectorised loop (aten's Mish lowers to three transcendental functions per value)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not torch.compiler.is_compiling():
            return nn.functional.mish(x)
        n = torch.exp(torch.clamp(x, max=20.0))  # beyond 20, n (n + 2) / (n (n + 2) + 2) is 1 in float32
        t = n * (n + 2.0)
        return x * t / (t + 2.0)


class ConvBlock(nn.Sequential):
    """Conv1d, GroupNorm(8), Mish."""

    def __init__(self, c_in: int, c_out: int, kernel_size: int) -> None:
        super().__init__(
            nn.Conv1d(c_in, c_out, kernel_size, padding=kernel_size // 2),
            nn.GroupNorm(8, c_out),
            Mish(),
        )


class ResidualTemporalBlock(nn.Module):
    """Two conv blocks with the time embedding added after the first, and a residual connection."""

    def __init__(self, c_in: int, c_out: int, embed_dim: int, kernel_size: int) -> None:
        super().__init__()
        self.first = ConvBlock(c_in, c_out, kernel_size)
        self.second = ConvBlock(c_out, c_out, kernel_size)
        self.time = nn.Sequential(Mish(), nn.Linear(embed_dim, c_out))
        self.residual = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        out = self.first(x) + self.time(emb)[:, :, None]
        return self.second(out) + self.residual(x)


def time_embedding(dim: int) -> nn.Sequential:
    """The diffusion-step embedding MLP shared by the U-Net and the value network."""
    return nn.Sequential(SinusoidalEmbedding(dim), nn.Linear(dim, dim * 4), Mish(), nn.Linear(dim * 4, dim))


def down_path(dims: list[int], embed_dim: int, kernel_size: int) -> nn.ModuleList:
    """The U-Net's contracting path: per channel pair two residual blocks, then a stride-2 downsample (none after
    the last pair)."""
    pairs = list(zip(dims[:-1], dims[1:], strict=True))
    return nn.ModuleList(
        nn.ModuleList(
            [
                ResidualTemporalBlock(c_in, c_out, embed_dim, kernel_size),
                ResidualTemporalBlock(c_out, c_out, embed_dim, kernel_size),
                nn.Conv1d(c_out, c_out, 3, stride=2, padding=1) if i < len(pairs) - 1 else nn.Identity(),
            ]
        )
        for i, (c_in, c_out) in enumerate(pairs)
    )


class TemporalUnet(nn.Module):
    """Diffuser's temporal U-Net: predicts a tensor of the input's shape from a noisy trajectory and step."""

    def __init__(
        self, transition_dim: int, dim: int = 32, dim_mults: tuple[int, ...] = (1, 4, 8), kernel_size: int = 5
    ) -> None:
        super().__init__()
        dims = [transition_dim, *(dim * m for m in dim_mults)]
        pairs = list(zip(dims[:-1], dims[1:], strict=True))
        self.downsample_factor = 2 ** (len(dim_mults) - 1)
        self.time_mlp = time_embedding(dim)
        self.down = down_path(dims, dim, kernel_size)
        mid = dims[-1]
        self.mid1 = ResidualTemporalBlock(mid, mid, dim, kernel_size)
        self.mid2 = ResidualTemporalBlock(mid, mid, dim, kernel_size)
        self.up = nn.ModuleList()
        for c_in, c_out in reversed(pairs[1:]):
            self.up.append(
                nn.ModuleList(
                    [
                        ResidualTemporalBlock(c_out * 2, c_in, dim, kernel_size),
                        ResidualTemporalBlock(c_in, c_in, dim, kernel_size),
                        nn.ConvTranspose1d(c_in, c_in, 4, stride=2, padding=1),
                    ]
                )
            )
        self.final = nn.Sequential(ConvBlock(dim, dim, kernel_size), nn.Conv1d(dim, transition_dim, 1))

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """``x``: ``[batch, horizon, transition_dim]``; ``t``: ``[batch]`` diffusion steps."""
        if x.shape[1] % self.downsample_factor:
            raise ValueError(f"horizon {x.shape[1]} is not divisible by {self.downsample_factor}")
        h = x.transpose(1, 2)
        emb = self.time_mlp(t)
        skips = []
        for block1, block2, downsample in self.down:
            h = block2(block1(h, emb), emb)
            skips.append(h)
            h = downsample(h)
        h = self.mid2(self.mid1(h, emb), emb)
        for block1, block2, upsample in self.up:
            h = torch.cat([h, skips.pop()], dim=1)
            h = upsample(block2(block1(h, emb), emb))
        return self.final(h).transpose(1, 2)
