"""Diffuser's value-guided replanning controller (the locomotion family's): at every step, the first action of the
best of N guided plans from the current state."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from adaptdiffuser.contract import Controller
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.diffusion.guidance import ValueGuidance
from adaptdiffuser.planning import Planner


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
