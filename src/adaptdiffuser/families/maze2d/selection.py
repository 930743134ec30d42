"""What the discriminator keeps of generated Maze2D trajectories beyond the generic rules: the paper's reward/length
rule with its thresholds per maze, and the check of coin tasks."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from adaptdiffuser.evolution.discriminator import TrackedTrajectory


@dataclass(frozen=True)
class PaperMazeRule:
    """The paper's Maze2D reward/length rule (appendix "Metric Values for Reward Discriminator"): keep when
    ``L > long_length`` or (``L > min_length`` and ``R + (episode_steps - L) > min_score``)."""

    episode_steps: int
    long_length: int
    min_length: int
    min_score: float

    def keeps(self, reward: float, length: int) -> bool:
        if length > self.long_length:
            return True
        return length > self.min_length and reward + (self.episode_steps - length) > self.min_score

    def select(self, returns: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """Positions of the trajectories the rule keeps (a
        :class:`~adaptdiffuser.evolution.discriminator.SelectionRule`)."""
        return np.flatnonzero([self.keeps(r, int(n)) for r, n in zip(returns, lengths, strict=True)])


# The appendix's thresholds per maze (U-Maze / Medium / Large).
PAPER_MAZE_RULES = {
    "umaze": PaperMazeRule(300, 200, 50, 210.0),
    "medium": PaperMazeRule(600, 450, 200, 400.0),
    "large": PaperMazeRule(800, 650, 270, 400.0),
}


def picks_coin_then_reaches_goal(trajectory: TrackedTrajectory, coin: np.ndarray, radius: float) -> bool:
    """The coin-aware reward: some state passes within ``radius`` of ``coin`` and a later (or the same) state
    is at the goal."""
    near = np.flatnonzero(np.linalg.norm(trajectory.observations[:, :2] - coin[None, :2], axis=1) <= radius)
    return bool(len(near)) and bool((trajectory.rewards[near[0] :] > 0).any())
