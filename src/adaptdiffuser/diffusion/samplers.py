"""One sampler interface, two implementations: the full DDPM chain and a strided deterministic DDIM; both take
optional guidance (reward-gradient or value, see :mod:`adaptdiffuser.diffusion.guidance`), combinable with
inpainting. Noise comes from a :class:`~adaptdiffuser.diffusion.noise.RowNoise` (counter-based, keyed by each row's
seed), so a row's sample does not depend on the rest of its batch."""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch

from adaptdiffuser.diffusion.conditions import Conditions, Projection, apply_inpainting
from adaptdiffuser.diffusion.gaussian import GaussianDiffusion
from adaptdiffuser.diffusion.guidance import GuidanceBase
from adaptdiffuser.diffusion.noise import RowNoise


class Sampler(ABC):
    """Draws trajectories ``[batch, horizon, transition_dim]`` from a diffusion model, inpainting conditions."""

    @abstractmethod
    def timesteps(self, diffusion: GaussianDiffusion) -> list[int]:
        """The diffusion steps visited, from noisiest to cleanest."""

    @abstractmethod
    def log_variance(self, diffusion: GaussianDiffusion, t: int, t_prev: int) -> torch.Tensor:
        """The log-variance (a scalar tensor) of the move from step ``t`` to ``t_prev``; ``-inf`` for none."""

    @abstractmethod
    def step(
        self, diffusion: GaussianDiffusion, x: torch.Tensor, t: int, t_prev: int, guidance: GuidanceBase | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The mean of one denoising move from step ``t`` to ``t_prev`` (``-1`` means the clean end), taken from the
        clean estimate as ``guidance.guide_estimate`` gives it (:func:`guided_estimate`), and the log-variance of that
        move (the noise a stochastic sampler adds, and the scale of guidance)."""

    #: whether :meth:`sample` adds noise of the step's variance (DDPM) or not (DDIM, eta = 0)
    stochastic: bool = False

    @torch.no_grad()
    def sample(
        self,
        diffusion: GaussianDiffusion,
        conditions: Conditions,
        noise: RowNoise,
        guidance: GuidanceBase | None = None,
        warm_start: tuple[torch.Tensor, int] | None = None,
        project: Projection | None = None,
    ) -> torch.Tensor:
        """Run the chain from pure noise; return normalized trajectories ``[len(noise), horizon, transition]``,
        row ``i`` drawing its initial and per-step noise from row ``i`` of ``noise`` only. With ``guidance``, each
        step first calls ``guidance.before_denoise`` on the noisy ``x`` (value guidance), lets
        ``guidance.guide_estimate`` move the denoiser's clean estimate, then adds ``guidance.mean_shift`` to the
        step's mean (reward guidance, paper Eq. 5) before noise and inpainting.
        ``project`` (a family's constraint) is applied after the inpainting, at the start and after every step.

        ``warm_start = (x0, t0)`` starts instead from the normalized trajectories ``x0`` noised to diffusion step
        ``t0`` (SDEdit-style partial noising) and visits only this sampler's steps below ``t0``: fewer network
        calls when a good guess exists, e.g. the previous decision's plan shifted by one step."""
        for t, value in conditions.items():
            if value.shape[0] != len(noise):
                raise ValueError(f"condition at step {t} has {value.shape[0]} rows but the noise has {len(noise)}")
        shape = (diffusion.horizon, diffusion.transition_dim)
        steps = self.timesteps(diffusion)
        if warm_start is None:
            x = noise.randn(shape)
        else:
            x0, t0 = warm_start
            if not 0 <= t0 < diffusion.n_steps:
                raise ValueError(f"warm start step must be in [0, {diffusion.n_steps - 1}], got {t0}")
            if tuple(x0.shape) != (len(noise), *shape):
                raise ValueError(f"warm start trajectories have shape {tuple(x0.shape)}, need {(len(noise), *shape)}")
            tt = torch.full((len(noise),), t0, device=x0.device, dtype=torch.long)
            x = diffusion.q_sample(x0, tt, noise.randn(shape))
            steps = [t0, *(t for t in steps if t < t0)]
        act_dim = diffusion.act_dim

        def constrain(x: torch.Tensor) -> torch.Tensor:
            x = apply_inpainting(x, conditions, act_dim)
            return x if project is None else project(x)

        x = constrain(x)
        for t, t_prev in zip(steps, [*steps[1:], -1], strict=True):
            if guidance is not None:
                x = guidance.before_denoise(x, t, self.log_variance(diffusion, t, t_prev).exp(), conditions, act_dim)
            mean, log_var = self.step(diffusion, x, t, t_prev, guidance)
            if guidance is not None:
                mean = mean + guidance.mean_shift(mean, log_var.exp())
            if self.stochastic and t_prev >= 0:
                mean = mean + (0.5 * log_var).exp() * noise.randn(x.shape[1:])
            x = constrain(mean)
        return x


def guided_estimate(
    diffusion: GaussianDiffusion, x: torch.Tensor, tt: torch.Tensor, guidance: GuidanceBase | None
) -> torch.Tensor:
    """The denoiser's clean estimate of ``x`` at steps ``tt``, as ``guidance.guide_estimate`` moves it when given."""
    x0 = diffusion.predict_x0(x, tt)
    return x0 if guidance is None else guidance.guide_estimate(x0)


class DDPMSampler(Sampler):
    """Ancestral sampling through every diffusion step."""

    def timesteps(self, diffusion: GaussianDiffusion) -> list[int]:
        return list(range(diffusion.n_steps - 1, -1, -1))

    stochastic = True

    def log_variance(self, diffusion: GaussianDiffusion, t: int, t_prev: int) -> torch.Tensor:
        return diffusion.posterior_log_variance[t]

    def step(self, diffusion, x, t, t_prev, guidance=None):
        tt = torch.full((x.shape[0],), t, device=x.device, dtype=torch.long)
        mean, _ = diffusion.posterior(guided_estimate(diffusion, x, tt, guidance), x, tt)
        return mean, self.log_variance(diffusion, t, t_prev)


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

    def log_variance(self, diffusion: GaussianDiffusion, t: int, t_prev: int) -> torch.Tensor:
        # the variance of the equivalent stochastic (DDPM) jump t -> t_prev, used only to scale guidance
        if t_prev < 0:
            return torch.full((), float("-inf"), device=diffusion.alphas_cumprod.device)
        ab, ab_prev = diffusion.alphas_cumprod[t], diffusion.alphas_cumprod[t_prev]
        variance = (1 - ab_prev) / (1 - ab) * (1 - ab / ab_prev)
        return variance.clamp(min=1e-20).log()

    def step(self, diffusion, x, t, t_prev, guidance=None):
        tt = torch.full((x.shape[0],), t, device=x.device, dtype=torch.long)
        x0 = guided_estimate(diffusion, x, tt, guidance)
        log_var = self.log_variance(diffusion, t, t_prev)
        if t_prev < 0:
            return x0, log_var
        ab, ab_prev = diffusion.alphas_cumprod[t], diffusion.alphas_cumprod[t_prev]
        eps = (x - ab.sqrt() * x0) / (1 - ab).sqrt()
        return ab_prev.sqrt() * x0 + (1 - ab_prev).sqrt() * eps, log_var


def make_sampler(kind: str, steps: int) -> Sampler:
    """The sampler named in params: ``ddpm`` (every step) or ``ddim`` with ``steps`` strided steps."""
    if kind == "ddpm":
        return DDPMSampler()
    if kind == "ddim":
        return DDIMSampler(steps)
    raise ValueError(f"unknown sampler {kind!r}; use 'ddpm' or 'ddim'")
