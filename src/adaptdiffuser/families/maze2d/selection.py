"""What the discriminator keeps of generated Maze2D trajectories beyond the generic rules: the paper's reward/length
rule with its thresholds per maze, the selection among closed-loop rollouts, and the check of coin tasks."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from adaptdiffuser.contract import TrackedTrajectory
    from adaptdiffuser.evolution.discriminator import SelectionRule


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


@dataclass(frozen=True)
class PaperReturnClause:
    """The return clause of :class:`PaperMazeRule` alone, for rollouts that end where they reach the goal: keep when
    ``R + (episode_steps - L) > min_score``, that is when the episode that arrives after ``L`` steps and stays earns
    more than the paper's threshold, so arrivals within 90 / 200 / 400 steps on U-Maze / Medium / Large. The rule's
    length clauses are left out: on arrival times ``L > long_length`` would keep the slowest arrivals, and with
    ``L > min_length`` the return clause admits no rollout at all on Medium (``L > 200`` and ``L < 201``)."""

    episode_steps: int
    min_score: float

    def select(self, returns: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """Positions of the rollouts that arrive early enough (a
        :class:`~adaptdiffuser.evolution.discriminator.SelectionRule`)."""
        scores = np.asarray(returns, dtype=np.float64) + (self.episode_steps - np.asarray(lengths, dtype=np.int64))
        return np.flatnonzero(scores > self.min_score)


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


@dataclass(frozen=True)
class RolloutRule:
    """Selection among rollouts, whose length ``L`` is the real one (steps until the goal is first reached, or the
    whole rollout when it never is) and whose return ``R`` is 1 when they reach the goal (they end there) and 0
    otherwise. Only rollouts that reach the goal are candidates; among them ``inner`` decides: the paper's return
    clause on ``(R, L)`` (:class:`PaperReturnClause`: ``R + (episode_steps - L)`` is exactly the protocol's return of
    an episode that reaches the goal after L steps and stays), or a generic rule (``quantile``, ``top_k``) ranking
    by that same episode return; either way shorter paths are preferred, as the author's recipe asks."""

    inner: SelectionRule
    episode_steps: int
    rank_by_episode_return: bool

    def select(self, returns: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        returns, lengths = np.asarray(returns, dtype=np.float64), np.asarray(lengths, dtype=np.int64)
        reached = np.flatnonzero(returns > 0)
        if not len(reached):
            return reached
        r, n = returns[reached], lengths[reached]
        scores = r + (self.episode_steps - n) if self.rank_by_episode_return else r
        return reached[self.inner.select(scores, n)]
