"""The one interface an environment implements to take part in planning, evolution and evaluation."""

from __future__ import annotations

from abc import abstractmethod

import numpy as np

from adaptdiffuser.families.base import Simulator


class PlanningEnv(Simulator):
    """A simulator with a task: reset, step, the protocol's reward, an expert, a tracking controller, a picture.

    Observations and actions are flat float vectors. One instance simulates one episode at a time; batch work
    (evaluation, tracking) holds one instance per parallel episode.
    """

    name: str
    obs_dim: int
    act_dim: int
    episode_steps: int

    @abstractmethod
    def reward(self, obs: np.ndarray) -> float:
        """The evaluation protocol's reward for being at ``obs``."""

    @abstractmethod
    def goal_state(self) -> np.ndarray:
        """The state the planner is conditioned to end in for the current task."""

    @abstractmethod
    def set_goal_state(self, goal: np.ndarray) -> None:
        """Make ``goal`` (a state, as :meth:`goal_state` returns) the current task's goal."""

    def tracking_error(self, executed: np.ndarray, planned: np.ndarray) -> float:
        """How far an executed state is from the planned one (full-state L2 unless an env says otherwise)."""
        return float(np.linalg.norm(np.asarray(executed) - np.asarray(planned)))

    @abstractmethod
    def seed_expert(self, seed: int) -> None:
        """Seed the expert's own randomness (for reproducible reference returns and data)."""

    @abstractmethod
    def expert_action(self, obs: np.ndarray) -> np.ndarray:
        """The scripted expert's action towards the current goal."""

    @abstractmethod
    def tracking_action(self, obs: np.ndarray, target: np.ndarray) -> np.ndarray:
        """The action that moves from ``obs`` towards the planned next state ``target``."""

    @abstractmethod
    def draw(
        self,
        ax,
        plan: np.ndarray | None = None,
        executed: np.ndarray | None = None,
        goal: np.ndarray | None = None,
    ) -> None:
        """Draw the task (optionally a planned and an executed state sequence, and the episode's goal state
        if it differs from the current one) on a matplotlib axis."""
