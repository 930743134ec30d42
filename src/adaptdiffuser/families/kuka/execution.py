"""Executing KUKA plans: open-loop plans of states replanned a fixed number of times per episode, and the
pick-and-place guidance."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from adaptdiffuser.contract import Controller
from adaptdiffuser.diffusion.guidance import GuidanceBase, Objective
from adaptdiffuser.families.kuka.scene import FLAG_COLUMNS, N_BLOCKS, N_JOINTS, block_position_columns
from adaptdiffuser.families.kuka.tasks import PLACE_TARGETS
from adaptdiffuser.seeding import derive_seed


def plan_commands(plan_states: np.ndarray) -> np.ndarray:
    """The commands ``[..., 11]`` (7 joint targets, 4 suction flags) that reach planned states ``[..., 39]``."""
    return np.concatenate([plan_states[..., :N_JOINTS], plan_states[..., list(FLAG_COLUMNS)]], axis=-1)


class PlaceObjective(Objective):
    """``J = -sum_{t >= first} ||xy of block b_i at t - its target||``: plan ``i`` carries block ``blocks[i]`` to
    its pick-and-place target over the plan's steps from ``first`` on."""

    def __init__(self, blocks: Sequence[int], first: int) -> None:
        self.first = first
        self.columns = torch.tensor([block_position_columns(b).start for b in blocks])
        self.targets = torch.as_tensor(PLACE_TARGETS[list(blocks), :2], dtype=torch.float32)

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        tail = states[:, self.first :, :]
        columns = self.columns.to(states.device)
        index = torch.stack([columns, columns + 1], dim=1)[:, None, :].expand(-1, tail.shape[1], -1)
        delta = torch.gather(tail, 2, index) - self.targets.to(states)[:, None, :]
        return -torch.sqrt((delta**2).sum(-1) + 1e-12).sum(-1)


class ReplanningController(Controller):
    """Plans ``horizon`` states from the current observation and executes them open loop, one planned state per
    step; replans every ``horizon - 1`` steps (so ``replans`` plans fill an episode). Plan ``r`` of episode ``e``
    is seeded by ``(seed, e, r)``; ``guidance(r, n)`` gives plan ``r``'s guidance for ``n`` episodes (or None).
    With ``record``, :attr:`recorded` collects each episode's planned states ``[T + 1, 39]`` (the start, then the
    state each step was commanded to reach), episodes in the order they ran."""

    def __init__(
        self,
        planner,
        seed: int,
        guidance: Callable[[int, int], GuidanceBase | None] | None = None,
        record: bool = False,
    ) -> None:
        self.planner = planner
        self.seed = seed
        self.guidance = guidance
        self.span = planner.horizon - 1
        self.record = record
        self.recorded: list[np.ndarray] = []

    def begin(self, envs, obs, episodes):
        self.episodes = list(episodes)
        self.first_plans = None
        self.plans: np.ndarray | None = None
        if self.record:
            self.batch_start = len(self.recorded)
            self.recorded.extend(o[None].copy() for o in obs)

    def act(self, envs, obs, t):
        step, replan = t % self.span, t // self.span
        if step == 0:
            seeds = [derive_seed(self.seed, e, replan) for e in self.episodes]
            guidance = self.guidance(replan, len(obs)) if self.guidance is not None else None
            self.plans = self.planner.plan(obs, None, seeds, guidance)[:, :, self.planner.act_dim :]
            if self.first_plans is None:
                self.first_plans = self.plans.copy()
            if self.record:
                for i, plan in enumerate(self.plans):
                    row = self.batch_start + i
                    self.recorded[row] = np.concatenate([self.recorded[row], plan[1:]])
        return plan_commands(self.plans[:, step + 1])


def place_guidance(planner, alpha: float, first: int) -> Callable[[int, int], GuidanceBase]:
    """Pick-and-place guidance: plan ``r`` pulls block ``r mod 4`` toward its target with scale ``alpha``."""

    def make(replan: int, n: int) -> GuidanceBase:
        return planner.guidance(PlaceObjective([replan % N_BLOCKS] * n, first), alpha)

    return make
