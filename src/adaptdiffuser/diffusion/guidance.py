"""Guidance of the denoising chain, one interface for two kinds.

:class:`GuidanceBase` has two hooks the samplers call at every step, never checking the concrete type:
``before_denoise`` (may move the noisy ``x`` before the denoiser sees it; default identity) and ``mean_shift``
(added to the step's mean; default zero). Both get the variance of the step: the DDPM posterior variance, or for
strided DDIM the variance of the equivalent stochastic jump (zero for the final jump to the clean end).

* :class:`Guidance` -- reward-gradient guidance (AdaptDiffuser paper Eq. 5, appendix A, Maze2D): the step's mean
  moves by ``alpha * variance * grad J``, where J is a differentiable objective of the trajectory in raw units; or
  (``on="x0"``, a third hook, ``guide_estimate``) the denoiser's clean estimate moves by ``alpha * grad J``.
* :class:`ValueGuidance` -- Diffuser's locomotion recipe: before each denoising step, ``n_guide_steps`` gradient
  ascent moves on a learned value ``V(x_t, t)``, each followed by re-inpainting; :meth:`ValueGuidance.values`
  scores finished samples so a controller can keep the best of N.

Reward sign convention: J is a *reward* (higher is better), so a positive ``alpha`` pulls plans toward what J
prefers (the Maze2D coin objective, :class:`~adaptdiffuser.families.maze2d.gold_coin.CoinObjective`, says how the
paper's negative scales map to ours).

Scale: the reward gradient is taken with respect to the *normalized* trajectory (the sampler's space) of J
evaluated on raw states, and multiplied by the variance of the step. With Maze2D's min/max normalizer (U-Maze
positions span about 2.1 maze units, mapped to a normalized range of 2), each state moves by about
``1.1 * alpha * variance`` normalized units per step.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable

import torch
from torch import nn

from adaptdiffuser.diffusion.conditions import Conditions, apply_inpainting


class Objective(ABC):
    """A differentiable score ``J`` of raw state sequences ``[batch, horizon, obs_dim]`` -> ``[batch]``."""

    @abstractmethod
    def __call__(self, states: torch.Tensor) -> torch.Tensor: ...


class GuidanceBase:
    """Hooks a sampler calls at each denoising step ``t`` (both are no-ops here; subclasses override one)."""

    def before_denoise(
        self, x: torch.Tensor, t: int, variance: torch.Tensor, conditions: Conditions, act_dim: int
    ) -> torch.Tensor:
        """The noisy trajectory the denoiser will see at step ``t`` (default: ``x`` unchanged)."""
        return x

    def mean_shift(self, mean: torch.Tensor, variance: torch.Tensor) -> torch.Tensor:
        """What to add to the step's mean before noise and inpainting (default: zero)."""
        return torch.zeros_like(mean)

    def guide_estimate(self, x0: torch.Tensor) -> torch.Tensor:
        """The denoiser's clean estimate ``x0`` the step is taken from (default: ``x0`` itself, nothing computed)."""
        return x0


class Guidance(GuidanceBase):
    """``alpha`` times the gradient of ``objective`` at a normalized trajectory; ``to_states`` maps a normalized
    trajectory ``[batch, horizon, transition]`` to raw states (differentiably). ``on="mean"`` (the paper's Eq. 5)
    adds ``alpha * variance * grad J`` to each step's mean; ``on="x0"`` adds ``alpha * grad J`` to the denoiser's
    clean estimate at every step, the last one included (whose variance is zero in DDIM), so that an x0-predicting
    model cannot pull the plan back where its prior lies."""

    def __init__(
        self,
        objective: Objective,
        alpha: float,
        to_states: Callable[[torch.Tensor], torch.Tensor],
        on: str = "mean",
    ) -> None:
        if on not in ("mean", "x0"):
            raise ValueError(f"guidance acts on 'mean' or 'x0', got {on!r}")
        self.objective = objective
        self.alpha = float(alpha)
        self.to_states = to_states
        self.on = on

    def shift(self, x: torch.Tensor, variance: torch.Tensor | float) -> torch.Tensor:
        """The guided move ``alpha * variance * dJ/dx`` at ``x`` (zero when ``alpha`` is zero)."""
        if self.alpha == 0.0:
            return torch.zeros_like(x)
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            score = self.objective(self.to_states(xg)).sum()
            (grad,) = torch.autograd.grad(score, xg)
        return self.alpha * variance * grad

    def mean_shift(self, mean: torch.Tensor, variance: torch.Tensor) -> torch.Tensor:
        """The sampler hook: :meth:`shift` (``on="mean"``)."""
        return self.shift(mean, variance) if self.on == "mean" else torch.zeros_like(mean)

    def guide_estimate(self, x0: torch.Tensor) -> torch.Tensor:
        """The sampler hook: the clean estimate moved by ``alpha * grad J`` (``on="x0"``; else unchanged)."""
        return x0 + self.shift(x0, 1.0) if self.on == "x0" else x0


class ValueGuidance(GuidanceBase):
    """Diffuser's value guidance. ``value_net(x, t)`` maps normalized noisy trajectories ``[batch, horizon,
    transition]`` and steps ``[batch]`` to values ``[batch]``. At each step ``t >= t_stopgrad``, ``n_guide_steps``
    times: ``x += scale * g`` with ``g = dV/dx`` (times the step's variance if ``scale_grad_by_std``, as Diffuser
    does despite the name), then the inpainting conditions are re-applied. Steps ``t < t_stopgrad`` are unguided.
    The network is used as given (put it in eval mode and on the sampler's device)."""

    def __init__(
        self,
        value_net: nn.Module,
        scale: float,
        n_guide_steps: int = 2,
        t_stopgrad: int = 2,
        scale_grad_by_std: bool = True,
    ) -> None:
        if n_guide_steps < 0:
            raise ValueError(f"n_guide_steps must be non-negative, got {n_guide_steps}")
        self.value_net = value_net
        self.scale = float(scale)
        self.n_guide_steps = int(n_guide_steps)
        self.t_stopgrad = int(t_stopgrad)
        self.scale_grad_by_std = scale_grad_by_std

    def gradient(self, x: torch.Tensor, t: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Values ``[batch]`` of ``x`` at step ``t`` and their gradient ``dV/dx``."""
        tt = torch.full((x.shape[0],), t, device=x.device, dtype=torch.long)
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            values = self.value_net(xg, tt)
            (grad,) = torch.autograd.grad(values.sum(), xg)
        return values.detach(), grad

    def before_denoise(
        self, x: torch.Tensor, t: int, variance: torch.Tensor, conditions: Conditions, act_dim: int
    ) -> torch.Tensor:
        """``n_guide_steps`` value-ascent moves of ``x`` at step ``t``, each re-inpainted."""
        if t < self.t_stopgrad or self.scale == 0.0:
            return x  # Diffuser zeroes the gradient here; skipping the value network gives the same x
        step = self.scale * variance if self.scale_grad_by_std else self.scale
        for _ in range(self.n_guide_steps):
            _, grad = self.gradient(x, t)
            x = apply_inpainting(x + step * grad, conditions, act_dim)
        return x

    @torch.no_grad()
    def values(self, x: torch.Tensor, t: int = 0) -> torch.Tensor:
        """The value ``[batch]`` of trajectories ``x`` at step ``t`` (``0``: finished samples), e.g. to pick the
        best of N plans with ``x[values.argmax()]``."""
        tt = torch.full((x.shape[0],), t, device=x.device, dtype=torch.long)
        return self.value_net(x, tt)
