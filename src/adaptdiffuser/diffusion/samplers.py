"""One sampler interface, two implementations: the full DDPM chain and a strided deterministic DDIM."""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch

from adaptdiffuser.diffusion.conditions import Conditions, apply_inpainting
from adaptdiffuser.diffusion.gaussian import GaussianDiffusion


class Sampler(ABC):
    """Draws trajectories ``[batch, horizon, transition_dim]`` from a diffusion model, inpainting conditions."""

    @abstractmethod
    def timesteps(self, diffusion: GaussianDiffusion) -> list[int]:
        """The diffusion steps visited, from noisiest to cleanest."""

    @abstractmethod
    def step(
        self, diffusion: GaussianDiffusion, x: torch.Tensor, t: int, t_prev: int, generator: torch.Generator
    ) -> torch.Tensor:
        """One denoising move from step ``t`` to ``t_prev`` (``-1`` means the clean end)."""

    @torch.no_grad()
    def sample(
        self, diffusion: GaussianDiffusion, batch: int, conditions: Conditions, generator: torch.Generator
    ) -> torch.Tensor:
        """Run the chain from pure noise; return normalized trajectories."""
        device = next(diffusion.parameters()).device
        shape = (batch, diffusion.horizon, diffusion.transition_dim)
        x = torch.randn(shape, device=device, generator=generator)
        x = apply_inpainting(x, conditions, diffusion.act_dim)
        steps = self.timesteps(diffusion)
        for t, t_prev in zip(steps, [*steps[1:], -1], strict=True):
            x = self.step(diffusion, x, t, t_prev, generator)
            x = apply_inpainting(x, conditions, diffusion.act_dim)
        return x


class DDPMSampler(Sampler):
    """Ancestral sampling through every diffusion step."""

    def timesteps(self, diffusion: GaussianDiffusion) -> list[int]:
        return list(range(diffusion.n_steps - 1, -1, -1))

    def step(self, diffusion, x, t, t_prev, generator):
        tt = torch.full((x.shape[0],), t, device=x.device, dtype=torch.long)
        mean, log_var = diffusion.posterior(diffusion.predict_x0(x, tt), x, tt)
        if t == 0:
            return mean
        noise = torch.randn(x.shape, device=x.device, generator=generator)
        return mean + (0.5 * log_var).exp() * noise


class DDIMSampler(Sampler):
    """Deterministic DDIM (eta = 0) over ``n_steps`` evenly strided diffusion steps."""

    def __init__(self, n_steps: int) -> None:
        if n_steps <= 0:
            raise ValueError(f"DDIM needs a positive number of steps, got {n_steps}")
        self.n_steps = n_steps

    def timesteps(self, diffusion: GaussianDiffusion) -> list[int]:
        n = min(self.n_steps, diffusion.n_steps)
        grid = torch.linspace(diffusion.n_steps - 1, 0, n).round().long().tolist()
        return list(dict.fromkeys(grid))

    def step(self, diffusion, x, t, t_prev, generator):
        tt = torch.full((x.shape[0],), t, device=x.device, dtype=torch.long)
        x0 = diffusion.predict_x0(x, tt)
        ab = diffusion.alphas_cumprod[t]
        if t_prev < 0:
            return x0
        ab_prev = diffusion.alphas_cumprod[t_prev]
        eps = (x - ab.sqrt() * x0) / (1 - ab).sqrt()
        return ab_prev.sqrt() * x0 + (1 - ab_prev).sqrt() * eps


def make_sampler(kind: str, steps: int) -> Sampler:
    """The sampler named in params: ``ddpm`` (every step) or ``ddim`` with ``steps`` strided steps."""
    if kind == "ddpm":
        return DDPMSampler()
    if kind == "ddim":
        return DDIMSampler(steps)
    raise ValueError(f"unknown sampler {kind!r}; use 'ddpm' or 'ddim'")
