"""One sampler interface, two implementations: the full DDPM chain and a strided deterministic DDIM; both take
optional reward-gradient guidance, combinable with inpainting."""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch

from adaptdiffuser.diffusion.conditions import Conditions, apply_inpainting
from adaptdiffuser.diffusion.gaussian import GaussianDiffusion
from adaptdiffuser.diffusion.guidance import Guidance


class Sampler(ABC):
    """Draws trajectories ``[batch, horizon, transition_dim]`` from a diffusion model, inpainting conditions."""

    @abstractmethod
    def timesteps(self, diffusion: GaussianDiffusion) -> list[int]:
        """The diffusion steps visited, from noisiest to cleanest."""

    @abstractmethod
    def step(
        self, diffusion: GaussianDiffusion, x: torch.Tensor, t: int, t_prev: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The mean of one denoising move from step ``t`` to ``t_prev`` (``-1`` means the clean end) and the
        log-variance of that move (the noise a stochastic sampler adds, and the scale of guidance)."""

    #: whether :meth:`sample` adds noise of the step's variance (DDPM) or not (DDIM, eta = 0)
    stochastic: bool = False

    @torch.no_grad()
    def sample(
        self,
        diffusion: GaussianDiffusion,
        batch: int,
        conditions: Conditions,
        generator: torch.Generator,
        guidance: Guidance | None = None,
    ) -> torch.Tensor:
        """Run the chain from pure noise; return normalized trajectories. With ``guidance``, each step's mean
        moves by ``alpha * variance * grad J`` before noise and inpainting (paper Eq. 5)."""
        device = next(diffusion.parameters()).device
        shape = (batch, diffusion.horizon, diffusion.transition_dim)
        x = torch.randn(shape, device=device, generator=generator)
        x = apply_inpainting(x, conditions, diffusion.act_dim)
        steps = self.timesteps(diffusion)
        for t, t_prev in zip(steps, [*steps[1:], -1], strict=True):
            mean, log_var = self.step(diffusion, x, t, t_prev)
            if guidance is not None:
                mean = mean + guidance.shift(mean, log_var.exp())
            if self.stochastic and t_prev >= 0:
                mean = mean + (0.5 * log_var).exp() * torch.randn(x.shape, device=x.device, generator=generator)
            x = apply_inpainting(mean, conditions, diffusion.act_dim)
        return x


class DDPMSampler(Sampler):
    """Ancestral sampling through every diffusion step."""

    def timesteps(self, diffusion: GaussianDiffusion) -> list[int]:
        return list(range(diffusion.n_steps - 1, -1, -1))

    stochastic = True

    def step(self, diffusion, x, t, t_prev):
        tt = torch.full((x.shape[0],), t, device=x.device, dtype=torch.long)
        mean, log_var = diffusion.posterior(diffusion.predict_x0(x, tt), x, tt)
        return mean, log_var


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

    def step(self, diffusion, x, t, t_prev):
        tt = torch.full((x.shape[0],), t, device=x.device, dtype=torch.long)
        x0 = diffusion.predict_x0(x, tt)
        ab = diffusion.alphas_cumprod[t]
        if t_prev < 0:
            return x0, torch.full((), float("-inf"), device=x.device)
        ab_prev = diffusion.alphas_cumprod[t_prev]
        eps = (x - ab.sqrt() * x0) / (1 - ab).sqrt()
        # the variance of the equivalent stochastic (DDPM) jump t -> t_prev, used only to scale guidance
        variance = (1 - ab_prev) / (1 - ab) * (1 - ab / ab_prev)
        return ab_prev.sqrt() * x0 + (1 - ab_prev).sqrt() * eps, variance.clamp(min=1e-20).log()


def make_sampler(kind: str, steps: int) -> Sampler:
    """The sampler named in params: ``ddpm`` (every step) or ``ddim`` with ``steps`` strided steps."""
    if kind == "ddpm":
        return DDPMSampler()
    if kind == "ddim":
        return DDIMSampler(steps)
    raise ValueError(f"unknown sampler {kind!r}; use 'ddpm' or 'ddim'")
