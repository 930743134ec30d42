"""The interfaces a benchmark family implements; the generic core (diffusion, planning, training, evaluation,
stages) works only through them and never names a maze, a robot or a block.

A family is one folder under ``families/`` and one line in :mod:`adaptdiffuser.families.registry`:

* :class:`Simulator`: the real dynamics of one episode: reset, reset to a stored full state, step with the real
  reward and termination, and a picture of an episode.
* :class:`Family`: builds the simulator of a task, makes the task's dataset, the score reference, the controller
  that turns plans into actions, and says whether its planner needs a value function. A family whose tasks
  evolve (``"evolve"`` in its task settings' ``OPTIONAL_STAGES``) also generates synthetic data with guidance and
  judges it in the simulator (:meth:`Family.generate`, :meth:`Family.discriminate`, :meth:`Family.selected_data`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from adaptdiffuser.data.d4rl import ExternalData
    from adaptdiffuser.data.schema import Trajectories
    from adaptdiffuser.evaluation import Controller, EpisodeBatchResult
    from adaptdiffuser.evolution.discriminator import Judgement


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
    """A benchmark family: everything the generic pipeline needs to know about its tasks. ``task`` arguments are
    :class:`~adaptdiffuser.config.TaskParams` (the family's own settings are ``task.settings``); ``paths`` is a
    :class:`~adaptdiffuser.families.base.TaskFiles` naming the task's files."""

    #: the ``family`` value of a task entry in params.yaml
    name: str

    #: which plan steps are inpainted (a name of :data:`adaptdiffuser.diffusion.conditions.CONDITIONINGS`)
    conditioning: str

    #: ``minmax`` or ``gaussian``: how trajectories are scaled for the model
    normalizer_kind: str

    #: whether the planner is guided by a learned value function (trained by the pretrain stage, after the model)
    uses_value_function: bool = False

    @abstractmethod
    def make_simulator(self, task: Any) -> Simulator:
        """A fresh simulator for ``task``."""

    @abstractmethod
    def collect(self, task: Any, files: TaskFiles, progress: bool) -> Trajectories:
        """The task's offline dataset (with file metadata); may write its own outputs (such as behaviour policies)
        under ``files.collect``."""

    @abstractmethod
    def reference(self, task: Any, files: TaskFiles, progress: bool) -> dict[str, Any]:
        """What 0 (``r_min``) and 100 (``r_max``) of the normalized score mean, plus any other reference figures."""

    @abstractmethod
    def controller(self, task: Any, planner: Any, files: TaskFiles, device: Any) -> Controller:
        """The controller that turns the planner's plans into actions in the simulator during evaluation."""

    def episode_columns(self, result: EpisodeBatchResult) -> dict[str, list[Any]]:
        """Family-specific columns of the per-episode results table (beside return, score, length...)."""
        return {}

    def episode_metrics(self, result: EpisodeBatchResult) -> dict[str, float]:
        """Family-specific evaluation metrics (beside the score's mean and standard error)."""
        return {}

    def extra_evaluations(self, task: Any, planner: Any, progress: bool) -> dict[str, float]:
        """Metrics of evaluations beside the task's score, run by the evaluate stage with the same planner (for
        example an unseen task, guided by the task's own settings); none by default."""
        return {}

    @abstractmethod
    def save_picture(
        self, task: Any, path: Path, plan: np.ndarray | None, executed: np.ndarray, title: str, goal: Any = None
    ) -> None:
        """One PNG of an evaluation episode: the first plan and the executed states."""

    def describe(self, task: Any) -> dict[str, Any]:
        """Facts about the task worth logging next to its runs (env id, dataset kind...)."""
        return {}

    # -- external data (the import stage and the Minari export) ------------------------------------------------------

    def from_external(self, task: Any, raw: ExternalData) -> Trajectories:
        """The task's dataset (with file metadata) from external data (a D4RL file or a Minari dataset, in their own
        coordinates); :class:`~adaptdiffuser.data.d4rl.DataImportError` naming the source, the field, the expected
        and the found dimension when the data does not fit the task's environment."""
        raise NotImplementedError(f"family {self.name!r} cannot import external data")

    def export_spec(self, task: Any) -> tuple[Any, Any, Any]:
        """``(env_spec, observation_space, action_space)`` for a Minari dataset of this task's data: the gymnasium
        ``EnvSpec`` of its environment (None when it has none) and the spaces of our observation and action rows."""
        import gymnasium as gym

        sim = self.make_simulator(task)
        box = gym.spaces.Box
        return None, box(-np.inf, np.inf, (sim.obs_dim,), np.float32), box(-np.inf, np.inf, (sim.act_dim,), np.float32)

    # -- evolution (families whose tasks evolve) --------------------------------------------------------------------

    def generate(
        self,
        task: Any,
        planner: Any,
        files: TaskFiles,
        cfg: Any,
        alpha: float,
        seed: int,
        generator: dict[str, Any],
        progress: bool,
    ) -> tuple[Trajectories, dict[str, float]]:
        """Synthetic plans of phase k (``cfg``: its ``GenerateParams``) from ``planner`` (phase k-1's model), for
        tasks the family samples with ``seed``; returns the plans as a dataset (``generator`` goes into its
        metadata) and statistics to log."""
        raise NotImplementedError(f"family {self.name!r} has no evolution phases")

    def discriminate(
        self, task: Any, generated: Trajectories, cfg: Any, phase: int, files: TaskFiles, progress: bool
    ) -> Judgement:
        """Execute each generated plan in the real simulator, reject those the dynamics cannot follow and select
        among the rest by real reward (``cfg``: phase ``phase``'s ``DiscriminateParams``)."""
        raise NotImplementedError(f"family {self.name!r} has no evolution phases")

    def selected_data(
        self, task: Any, generated: Trajectories, judgement: Judgement, generator: dict[str, Any]
    ) -> Trajectories:
        """The kept executed trajectories as a dataset (``generator``: metadata of how they were made)."""
        raise NotImplementedError(f"family {self.name!r} has no evolution phases")


@dataclass(frozen=True)
class TaskFiles:
    """The files of one task under the pipeline's root (paths from :mod:`adaptdiffuser.stages.common`)."""

    root: Path
    task: str
    #: the model folder in use (``models/<task>/phase<k>/seed<s>``, relative to ``root``); None = the phase-0
    #: model of training seed ``seed``
    model: Path | None = None
    #: the training seed the stage works for
    seed: int = 0

    @property
    def dataset(self) -> Path:
        from adaptdiffuser.stages.common import dataset_path

        return self.root / dataset_path(self.task)

    @property
    def value(self) -> Path:
        """The value function beside the model in use (fine-tuning carries phase 0's into every later model)."""
        from adaptdiffuser.stages.common import value_dir

        return (
            self.root / self.model / "value" if self.model is not None else self.root / value_dir(self.task, self.seed)
        )

    @property
    def collect(self) -> Path:
        """The collect stage's folder: its summary and the family's own outputs, such as behaviour policies."""
        from adaptdiffuser.stages.common import collect_dir

        return self.root / collect_dir(self.task)
