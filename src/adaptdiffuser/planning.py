"""Planning with a trained model: batched sampling of plans, and the value-guided replanning controller (controllers
that follow a plan's states are a family's own, in its folder)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from adaptdiffuser.checkpoint import ModelBundle
from adaptdiffuser.contract import Controller
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.diffusion.conditions import Projection
from adaptdiffuser.diffusion.guidance import Guidance, GuidanceBase, Objective, ValueGuidance
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


def shift_plans(x: torch.Tensor) -> torch.Tensor:
    """Plans ``[batch, horizon, transition]`` advanced by one step: drop the first, repeat the last."""
    return torch.cat([x[:, 1:], x[:, -1:]], dim=1)


class ValuePlanningController(Controller):
    """Diffuser's locomotion controller: at every step, sample ``n_samples`` start-conditioned plans per episode
    from the current observation (all episodes in one batch, each plan seeded by its episode, step and sample
    index, see :meth:`seeds`), guided by the learned value, and execute the first action of each episode's
    highest-value plan. Episodes that have ended are not planned for. The plans of step 0 are kept for pictures.

    With ``warm_start_step`` set, every decision after an episode's first starts its samples from the plan it
    executed last, shifted by one step and noised to that diffusion step, instead of from pure noise: the chain
    then visits only the sampler's steps below it (fewer network calls; score and speed: docs/speed.md)."""

    def __init__(
        self,
        planner: Planner,
        guidance: ValueGuidance,
        n_samples: int,
        seed: int,
        warm_start_step: int | None = None,
    ) -> None:
        if n_samples <= 0:
            raise ValueError(f"n_samples must be positive, got {n_samples}")
        n_steps = planner.model.n_steps
        if warm_start_step is not None and not 0 <= warm_start_step < n_steps:
            raise ValueError(f"warm_start_step must be in [0, {n_steps - 1}] (diffusion steps), got {warm_start_step}")
        self.planner = planner
        self.guidance = guidance
        self.n_samples = n_samples
        self.seed = seed
        self.warm_start_step = warm_start_step

    def seeds(self, episodes: Sequence[int], t: int) -> list[int]:
        """The seeds of the plans sampled at step ``t``: sample ``j`` of episode ``e`` uses ``(seed, e, t, j)``,
        rows in the order of ``np.repeat(obs, n_samples, axis=0)``."""
        return [derive_seed(self.seed, e, t, j) for e in episodes for j in range(self.n_samples)]

    def begin(self, envs, obs, episodes):
        self.episodes = episodes
        self.first_plans = None
        self.last_plans: torch.Tensor | None = None

    def act(self, envs, obs, t):
        n = self.n_samples
        rows = np.flatnonzero(self.active_rows(len(obs)))
        warm = None
        if self.warm_start_step is not None and self.last_plans is not None:
            warm = (shift_plans(self.last_plans[rows]).repeat_interleave(n, dim=0), self.warm_start_step)
        episodes = [self.episodes[i] for i in rows]
        x = self.planner.sample(np.repeat(obs[rows], n, axis=0), None, self.seeds(episodes, t), self.guidance, warm)
        values = self.guidance.values(x).reshape(len(rows), n)
        best = values.argmax(dim=1) + torch.arange(len(rows), device=x.device) * n
        chosen = x[best]
        if self.last_plans is None:
            self.last_plans = torch.zeros((len(obs), *chosen.shape[1:]), dtype=chosen.dtype, device=chosen.device)
        self.last_plans[rows] = chosen
        if self.first_plans is None:
            plans = self.planner.normalizer.unnormalize(self.last_plans.double().cpu().numpy())
            self.first_plans = plans[:, :, self.planner.act_dim :]
        actions = np.zeros((len(obs), self.planner.act_dim))
        actions[rows] = self.planner.actions(chosen)
        return actions
