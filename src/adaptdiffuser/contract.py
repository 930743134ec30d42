"""The contract between the generic core and the benchmark families: the types both sides use. At run time it
imports nothing of the project but :mod:`adaptdiffuser.layout` (the file layout); its types also name config, data
and the planner (imported for type checking), so it sits above those and below everything that uses it.

A family is one folder under ``families/`` and one line in :mod:`adaptdiffuser.family_registry`:

* :class:`Simulator`: the real dynamics of one episode: reset, reset to a stored full state, step with the real
  reward and termination, and a picture of an episode.
* :class:`Controller`: turns observations (and plans) into actions for a batch of simulators in lock-step;
  :class:`EpisodeBatchResult` is what an evaluation of it records.
* :class:`Family`: builds the simulator of a task, makes the task's dataset, the score reference, the controller
  that turns plans into actions, and says whether its planner needs a value function. A family whose tasks
  evolve (``"evolve"`` in its task settings' ``OPTIONAL_STAGES``) also generates synthetic data with guidance and
  judges it in the simulator (:meth:`Family.generate`, :meth:`Family.discriminate`, :meth:`Family.selected_data`),
  the verdict being a :class:`Judgement` over :class:`TrackedTrajectory` executions.
* :class:`TaskFiles`: the files of one task a family reads and writes.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, TypeVar

import numpy as np

from adaptdiffuser.layout import collect_dir, collect_resume_path, dataset_path, value_dir

if TYPE_CHECKING:  # types only (still layers below the contract): at run time it imports only the layout
    import torch
    from gymnasium import Space
    from gymnasium.envs.registration import EnvSpec

    from adaptdiffuser.config.sections import DiscriminateParams, GenerateParams
    from adaptdiffuser.config.tasks import TaskParams
    from adaptdiffuser.data.d4rl import ExternalData
    from adaptdiffuser.data.schema import Trajectories
    from adaptdiffuser.planning import Planner

#: the type of a family's task settings (its ``TASK_PARAMS``)
SettingsT = TypeVar("SettingsT")


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


class Controller:
    """Chooses actions for a batch of environments running in lock-step."""

    #: the state sequences planned at t = 0 for the current batch, if the controller plans (for pictures)
    first_plans: np.ndarray | None = None
    #: which rows of the batch are still running, set by :func:`run_episodes` before each :meth:`act` (``None``:
    #: all); a controller may skip the others, whose actions are never executed
    active: np.ndarray | None = None

    def active_rows(self, n: int) -> np.ndarray:
        """The boolean mask of the ``n`` rows still running."""
        return np.ones(n, dtype=bool) if self.active is None else self.active

    def begin(self, envs: list[Simulator], obs: np.ndarray, episodes: list[int]) -> None:
        """Called once per batch after reset."""

    def act(self, envs: list[Simulator], obs: np.ndarray, t: int) -> np.ndarray:
        raise NotImplementedError


@dataclass
class EpisodeBatchResult:
    """Per-episode outcomes of an evaluation run."""

    episodes: list[int] = field(default_factory=list)
    returns: list[float] = field(default_factory=list)
    final_success: list[bool] = field(default_factory=list)
    first_goal_step: list[int] = field(default_factory=list)
    starts: list[np.ndarray] = field(default_factory=list)
    goals: list[np.ndarray] = field(default_factory=list)
    executed: list[np.ndarray] = field(default_factory=list)
    plans: list[np.ndarray | None] = field(default_factory=list)
    lengths: list[int] = field(default_factory=list)
    terminated: list[bool] = field(default_factory=list)


@dataclass
class TrackedTrajectory:
    """A plan executed by the tracking controller: real observations ``[H, obs]`` and the actions taken in each
    of them ``[H, act]`` (the last one is the follower's action past the plan's end, so the trajectory fills a
    training window of length H), the tracking error of each step ``[H - 1]``,
    the protocol reward of each executed state ``[H]`` (as in the expert data) and the first step at the goal."""

    observations: np.ndarray
    actions: np.ndarray
    errors: np.ndarray
    rewards: np.ndarray
    steps_to_goal: int

    @property
    def max_error(self) -> float:
        return float(self.errors.max()) if len(self.errors) else 0.0

    @property
    def mean_error(self) -> float:
        return float(self.errors.mean()) if len(self.errors) else 0.0

    @property
    def total_reward(self) -> float:
        return float(self.rewards.sum())


@dataclass
class Judgement:
    """The discriminator's verdict on generated plans: the trajectories it judged (executed, or planned when
    tracking is off), which passed tracking, the indices kept (best first where the rule ranks) and any counts
    of the family's own for the report (``details``)."""

    trajectories: list[TrackedTrajectory]
    passed_tracking: np.ndarray
    kept: np.ndarray
    details: dict[str, int | float] = field(default_factory=dict)

    def report(self) -> dict[str, float | int]:
        """Counts and distributions for the stage report and ``metrics/summary.json``."""
        n = len(self.trajectories)
        passed = int(self.passed_tracking.sum())
        mean_errors = np.array([t.mean_error for t in self.trajectories])
        returns = np.array([t.total_reward for t in self.trajectories])
        return {
            "generated": n,
            "rejected_tracking": n - passed,
            "rejected_reward": passed - len(self.kept),
            "kept": len(self.kept),
            "kept_fraction": len(self.kept) / n if n else 0.0,
            "tracking_error_mean": float(mean_errors.mean()) if n else 0.0,
            "return_mean": float(returns.mean()) if n else 0.0,
            "return_mean_kept": float(returns[self.kept].mean()) if len(self.kept) else 0.0,
            **self.details,
        }


class Family(ABC, Generic[SettingsT]):
    """A benchmark family: everything the generic pipeline needs to know about its tasks. ``task`` arguments are
    :class:`~adaptdiffuser.config.TaskParams` whose ``settings`` are the family's own (``SettingsT``, its
    ``TASK_PARAMS``: a family subclasses ``Family[<its settings model>]``); ``files`` is a :class:`TaskFiles` naming
    the task's files."""

    #: the ``family`` value of a task entry in params.yaml
    name: str

    #: which plan steps are inpainted (a name of :data:`adaptdiffuser.diffusion.conditions.CONDITIONINGS`)
    conditioning: str

    #: ``minmax`` or ``gaussian``: how trajectories are scaled for the model
    normalizer_kind: str

    #: whether the planner is guided by a learned value function (trained by the pretrain stage, after the model)
    uses_value_function: bool = False

    @abstractmethod
    def make_simulator(self, task: TaskParams[SettingsT]) -> Simulator:
        """A fresh simulator for ``task``."""

    @abstractmethod
    def collect(self, task: TaskParams[SettingsT], files: TaskFiles, progress: bool) -> Trajectories:
        """The task's offline dataset (with file metadata); may write its own outputs (such as behaviour policies)
        under ``files.collect``."""

    @abstractmethod
    def reference(self, task: TaskParams[SettingsT], files: TaskFiles, progress: bool) -> dict[str, Any]:
        """What 0 (``r_min``) and 100 (``r_max``) of the normalized score mean, plus any other reference figures."""

    @abstractmethod
    def controller(
        self, task: TaskParams[SettingsT], planner: Planner, files: TaskFiles, device: torch.device
    ) -> Controller:
        """The controller that turns the planner's plans into actions in the simulator during evaluation."""

    def episode_columns(self, result: EpisodeBatchResult) -> dict[str, list[Any]]:
        """Family-specific columns of the per-episode results table (beside return, score, length...)."""
        return {}

    def episode_metrics(self, result: EpisodeBatchResult) -> dict[str, float]:
        """Family-specific evaluation metrics (beside the score's mean and standard error)."""
        return {}

    #: the name of the family's unseen task evaluated by :meth:`evaluate_unseen` (the key of its metrics and the
    #: task section holding its settings), or None
    unseen_task: str | None = None

    def evaluate_unseen(
        self,
        task: TaskParams[SettingsT],
        planner: Planner,
        alpha: float,
        ref: dict[str, Any],
        pictures: Path,
        title: str,
        progress: bool,
    ) -> dict[str, float]:
        """The planner on the family's unseen task, guided with scale ``alpha`` (the top-level ``alpha``): its
        metrics; pictures of some episodes written under ``pictures`` (an existing folder), titled starting with
        ``title``; ``ref`` is the task's score reference."""
        raise NotImplementedError(f"family {self.name!r} has no unseen task")

    def unseen_objective(self, metrics: dict[str, Any]) -> float:
        """The one figure of :meth:`evaluate_unseen`'s metrics that a sweep maximises on the unseen task (0-100)."""
        raise NotImplementedError(f"family {self.name!r} has no unseen task")

    @abstractmethod
    def save_picture(
        self,
        task: TaskParams[SettingsT],
        path: Path,
        plan: np.ndarray | None,
        executed: np.ndarray,
        title: str,
        goal: np.ndarray | None = None,
    ) -> None:
        """One PNG of an evaluation episode: the first plan and the executed states."""

    def describe(self, task: TaskParams[SettingsT]) -> dict[str, Any]:
        """Facts about the task worth logging next to its runs (env id, dataset kind...)."""
        return {}

    # -- external data (the import stage and the Minari export) ------------------------------------------------------

    def from_external(self, task: TaskParams[SettingsT], raw: ExternalData) -> Trajectories:
        """The task's dataset (with file metadata) from external data (a D4RL file or a Minari dataset, in their own
        coordinates); :class:`~adaptdiffuser.data.d4rl.DataImportError` naming the source, the field, the expected
        and the found dimension when the data does not fit the task's environment."""
        raise NotImplementedError(f"family {self.name!r} cannot import external data")

    def export_spec(self, task: TaskParams[SettingsT]) -> tuple[EnvSpec | None, Space, Space]:
        """``(env_spec, observation_space, action_space)`` for a Minari dataset of this task's data: the gymnasium
        ``EnvSpec`` of its environment (None when it has none) and the spaces of our observation and action rows."""
        import gymnasium as gym

        sim = self.make_simulator(task)
        box = gym.spaces.Box
        return None, box(-np.inf, np.inf, (sim.obs_dim,), np.float32), box(-np.inf, np.inf, (sim.act_dim,), np.float32)

    # -- evolution (families whose tasks evolve) --------------------------------------------------------------------

    def generate(
        self,
        task: TaskParams[SettingsT],
        planner: Planner,
        files: TaskFiles,
        cfg: GenerateParams,
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
        self,
        task: TaskParams[SettingsT],
        generated: Trajectories,
        cfg: DiscriminateParams,
        phase: int,
        files: TaskFiles,
        progress: bool,
    ) -> Judgement:
        """Execute each generated plan in the real simulator, reject those the dynamics cannot follow and select
        among the rest by real reward (``cfg``: phase ``phase``'s ``DiscriminateParams``)."""
        raise NotImplementedError(f"family {self.name!r} has no evolution phases")

    def selected_data(
        self, task: TaskParams[SettingsT], generated: Trajectories, judgement: Judgement, generator: dict[str, Any]
    ) -> Trajectories:
        """The kept executed trajectories as a dataset (``generator``: metadata of how they were made)."""
        raise NotImplementedError(f"family {self.name!r} has no evolution phases")


@dataclass(frozen=True)
class TaskFiles:
    """The files of one task under the pipeline's root (paths from :mod:`adaptdiffuser.layout`)."""

    root: Path
    task: str
    #: the model folder in use (``models/<task>/phase<k>/seed<s>``, relative to ``root``); None = the phase-0
    #: model of training seed ``seed``
    model: Path | None = None
    #: the training seed the stage works for
    seed: int = 0
    #: the digest of the task's code (its ``code`` stage's fingerprint), which a recipe tags its resume state with so
    #: that other code does not take it up; None outside the pipeline
    code: str | None = None

    @property
    def dataset(self) -> Path:

        return self.root / dataset_path(self.task)

    @property
    def value(self) -> Path:
        """The value function beside the model in use (fine-tuning carries phase 0's into every later model)."""

        return (
            self.root / self.model / "value" if self.model is not None else self.root / value_dir(self.task, self.seed)
        )

    @property
    def collect(self) -> Path:
        """The collect stage's folder: its summary and the family's own outputs, such as behaviour policies."""

        return self.root / collect_dir(self.task)

    @property
    def collect_resume(self) -> Path:
        """Where a family's data recipe may keep its state under way, to continue after an interruption."""

        return self.root / collect_resume_path(self.task)
