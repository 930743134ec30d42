"""The interfaces a benchmark family implements; the generic core (diffusion, planning, training, evaluation,
stages) works only through them and never names a maze, a robot or a block.

A family is one folder under ``families/`` and one line in :mod:`adaptdiffuser.families.registry`:

* :class:`Simulator`: the real dynamics of one episode: reset, reset to a stored full state, step with the real
  reward and termination, and a picture of an episode.
* :class:`Family`: builds the simulator of a task, makes the task's dataset, the score reference, the controller
  that turns plans into actions, and says whether its planner needs a value function.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Step:
    """What one simulator step returns: the next observation, the real reward of the transition and whether
    the episode ended by termination (a fall); running out of time is the evaluation loop's business."""

    observation: np.ndarray
    reward: float
    terminated: bool


class Simulator(ABC):
    """One episode at a time of a real simulator with the task's reward.

    Observations and actions are flat float vectors; ``get_state``/``set_state`` move the full simulator state
    (for MuJoCo: qpos and qvel), which may hold more than the observation.
    """

    name: str
    obs_dim: int
    act_dim: int
    state_dim: int
    episode_steps: int

    @abstractmethod
    def reset(self, rng: np.random.Generator) -> np.ndarray:
        """Start an episode from the protocol's start distribution; return the first observation."""

    @abstractmethod
    def get_state(self) -> np.ndarray:
        """The full simulator state now."""

    @abstractmethod
    def set_state(self, state: np.ndarray) -> np.ndarray:
        """Put the simulator exactly at ``state`` (as :meth:`get_state` returns it); return the observation."""

    @abstractmethod
    def step(self, action: np.ndarray) -> Step:
        """Apply one action."""

    def goal_state(self) -> np.ndarray | None:
        """The state the current task asks to reach, for tasks that have one (recorded with each episode)."""
        return None


class Family(ABC):
    """A benchmark family: everything the generic pipeline needs to know about its tasks."""

    #: the ``family`` value of a task entry in params.yaml
    name: str

    #: which plan steps are inpainted (a name of :data:`adaptdiffuser.diffusion.conditions.CONDITIONINGS`)
    conditioning: str

    def uses_value_function(self, task: Any) -> bool:
        """Whether the task's planner is guided by a learned value function (trained by the value stage)."""
        return False

    @abstractmethod
    def make_simulator(self, task: Any) -> Simulator:
        """A fresh simulator for ``task`` (the task's resolved params)."""

    @abstractmethod
    def normalizer_kind(self) -> str:
        """``minmax`` or ``gaussian``: how trajectories are scaled for the model."""

    def describe(self, task: Any) -> dict[str, Any]:
        """Facts about the task worth logging next to its runs (env id, dataset kind...)."""
        return {}
