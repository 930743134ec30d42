"""The one interface an environment implements to take part in planning, evolution and evaluation."""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np


class PlanningEnv(ABC):
    """A simulator with a task: reset, step, the protocol's reward, an expert, a tracking controller, a picture.

    Observations and actions are flat float vectors. One instance simulates one episode at a time; batch work
    (evaluation, tracking) holds one instance per parallel episode.
    """

    name: str
    obs_dim: int
    act_dim: int
    episode_steps: int

    @abstractmethod
    def reset(self, rng: np.random.Generator) -> np.ndarray:
        """Start an episode from the protocol's start distribution; return the first observation."""

    @abstractmethod
    def set_state(self, obs: np.ndarray) -> np.ndarray:
        """Put the simulator exactly at the state ``obs``; return the observation it now reports."""

    @abstractmethod
    def step(self, action: np.ndarray) -> np.ndarray:
        """Apply one action; return the next observation (episodes never end early)."""

    @abstractmethod
    def reward(self, obs: np.ndarray) -> float:
        """The evaluation protocol's reward for being at ``obs``."""

    @abstractmethod
    def expert_action(self, obs: np.ndarray) -> np.ndarray:
        """The scripted expert's action towards the current goal."""

    @abstractmethod
    def tracking_action(self, obs: np.ndarray, target: np.ndarray) -> np.ndarray:
        """The action that moves from ``obs`` towards the planned next state ``target``."""

    @abstractmethod
    def draw(self, ax, plan: np.ndarray | None = None, executed: np.ndarray | None = None) -> None:
        """Draw the task (and optionally a planned and an executed state sequence) on a matplotlib axis."""
