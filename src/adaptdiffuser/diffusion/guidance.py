"""Reward-gradient guidance (paper Eq. 5, appendix A): at each denoising step the mean moves by
``alpha * variance * grad J``, where J is a differentiable objective of the trajectory in raw units.

Sign convention: J is a *reward* (higher is better), so a positive ``alpha`` pulls plans toward what J prefers.
The paper writes the coin objective as the distance ``sum_t ||s_t - s_c||_2`` and, for the Diffuser baseline,
uses negative scales ({-50, -100, -200}); our :class:`CoinObjective` is the negative of that distance, so the
paper's ``alpha = -50`` on the distance is our ``alpha = 50``.

Scale: the gradient is taken with respect to the *normalized* trajectory (the sampler's space) of J evaluated on
raw states, and multiplied by the variance of the step (the DDPM posterior variance; for strided DDIM the
variance of the equivalent stochastic jump). With Maze2D's min/max normalizer (U-Maze positions span about 2.1
maze units, mapped to a normalized range of 2), each state moves by about ``1.1 * alpha * variance``
normalized units per step.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable

import torch


class Objective(ABC):
    """A differentiable score ``J`` of raw state sequences ``[batch, horizon, obs_dim]`` -> ``[batch]``."""

    @abstractmethod
    def __call__(self, states: torch.Tensor) -> torch.Tensor: ...


class CoinObjective(Objective):
    """``J = -sum_t ||xy_t - coin||_2``: the closer the whole plan passes to its coin, the higher. ``coins`` is
    ``[batch, 2]`` (one coin per plan) in maze coordinates."""

    def __init__(self, coins: torch.Tensor, eps: float = 1e-6) -> None:
        self.coins = coins
        self.eps = eps

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        delta = states[..., :2] - self.coins.to(states)[:, None, :]
        return -torch.sqrt((delta**2).sum(-1) + self.eps**2).sum(-1)


class Guidance:
    """``alpha`` times the gradient of ``objective`` at a normalized trajectory; ``to_states`` maps a normalized
    trajectory ``[batch, horizon, transition]`` to raw states (differentiably)."""

    def __init__(self, objective: Objective, alpha: float, to_states: Callable[[torch.Tensor], torch.Tensor]) -> None:
        self.objective = objective
        self.alpha = float(alpha)
        self.to_states = to_states

    def shift(self, x: torch.Tensor, variance: torch.Tensor | float) -> torch.Tensor:
        """The guided move ``alpha * variance * dJ/dx`` at ``x`` (zero when ``alpha`` is zero)."""
        if self.alpha == 0.0:
            return torch.zeros_like(x)
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            score = self.objective(self.to_states(xg)).sum()
            (grad,) = torch.autograd.grad(score, xg)
        return self.alpha * variance * grad
