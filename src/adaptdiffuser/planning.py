"""Planning with a trained model: batched sampling of plans. Controllers, which turn plans into actions, are a
family's own, in its folder (the value-guided replanning controller is the locomotion family's)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from adaptdiffuser.checkpoint import ModelBundle
from adaptdiffuser.diffusion.conditions import Projection
from adaptdiffuser.diffusion.guidance import Guidance, GuidanceBase, Objective
from adaptdiffuser.diffusion.noise import RowNoise
from adaptdiffuser.diffusion.samplers import Sampler
from adaptdiffuser.models.compiled import compile_network


class Planner:
    """Samples state-action plans from start to goal with the EMA model of a bundle (its network compiled when
    ``compiled``: the first batch of each shape compiles, docs/speed.md)."""

    def __init__(self, bundle: ModelBundle, sampler: Sampler, device: torch.device, compiled: bool = False) -> None:
        self.model = bundle.ema.to(device).eval()
        if compiled:
            compile_network(self.model.model, device, "compile.sampling")  # the bundle's EMA network, in place
        self.normalizer = bundle.normalizer
        self.sampler = sampler
        self.device = device
        self.act_dim = bundle.config["act_dim"]
        #: ``start_goal`` (plans inpaint the start and the goal) or ``start`` (the start only)
        self.conditioning = bundle.config.get("conditioning", "start_goal")
        self.horizon = self.model.horizon
        #: the network's floating-point type: conditions and noise are made in it (float32 unless a caller
        #: converted the bundle, e.g. to float64 for tests that must not depend on float32 rounding)
        self.dtype = next(self.model.parameters()).dtype

    def _normalize_states(self, states: np.ndarray) -> torch.Tensor:
        padded = np.concatenate([np.zeros((len(states), self.act_dim)), states], axis=1)
        normed = self.normalizer.normalize(padded)[:, self.act_dim :]
        return torch.as_tensor(normed, dtype=self.dtype, device=self.device)

    def guidance(self, objective: Objective, alpha: float, on: str = "mean") -> Guidance:
        """Guidance by ``objective`` (a function of raw states) with scale ``alpha``, acting on each step's mean or
        on the denoiser's clean estimate (``on``, :class:`Guidance`), for :meth:`plan`."""
        return Guidance(objective, alpha, lambda x: self.normalizer.unnormalize(x)[..., self.act_dim :], on)

    def plan(
        self,
        starts: np.ndarray,
        goals: np.ndarray | None,
        seeds: Sequence[int] | np.ndarray,
        guidance: GuidanceBase | None = None,
        project: Projection | None = None,
    ) -> np.ndarray:
        """Plans ``[batch, horizon, act_dim + obs_dim]`` in raw units from ``starts`` (and to ``goals`` when the
        model is goal-conditioned; ``None`` for start-conditioned models), optionally guided and constrained by
        ``project`` (see :meth:`Sampler.sample`). ``seeds`` holds one seed per row: a row's plan depends on its own
        seed, start, goal and guidance, not on the other rows."""
        x = self.sample(starts, goals, seeds, guidance, project=project)
        return self.normalizer.unnormalize(x.double().cpu().numpy())

    def sample(
        self,
        starts: np.ndarray,
        goals: np.ndarray | None,
        seeds: Sequence[int] | np.ndarray,
        guidance: GuidanceBase | None = None,
        warm_start: tuple[torch.Tensor, int] | None = None,
        project: Projection | None = None,
    ) -> torch.Tensor:
        """Like :meth:`plan`, but the normalized trajectories as a tensor on the planner's device; ``warm_start``
        (normalized trajectories, diffusion step) as in :meth:`Sampler.sample`."""
        noise = RowNoise(seeds, self.device, self.dtype)
        if len(noise) != len(starts):
            raise ValueError(f"{len(starts)} starts but {len(noise)} seeds; give one seed per row")
        conditions = {0: self._normalize_states(starts)}
        if goals is not None:
            conditions[self.horizon - 1] = self._normalize_states(goals)
        return self.sampler.sample(self.model, conditions, noise, guidance, warm_start, project)

    def actions(self, x: torch.Tensor) -> np.ndarray:
        """The raw first actions ``[batch, act_dim]`` of normalized trajectories ``x``."""
        return self.normalizer.unnormalize(x[:, 0].double().cpu().numpy())[:, : self.act_dim]
