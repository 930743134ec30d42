"""The locomotion family as the generic pipeline sees it (registered in ``family_registry.py``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from adaptdiffuser.config import TaskParams
from adaptdiffuser.contract import Controller, EpisodeBatchResult, Family, TaskFiles
from adaptdiffuser.data.schema import Trajectories, read_trajectories
from adaptdiffuser.evaluation import standard_error
from adaptdiffuser.families.locomotion.params import LocomotionTaskParams, parse_task_name
from adaptdiffuser.families.locomotion.reference import REFERENCE_RETURNS, normalized_score, robot_of
from adaptdiffuser.families.locomotion.simulator import LocomotionSimulator
from adaptdiffuser.plots import save_series_picture


def episode_returns(traj: Trajectories) -> np.ndarray:
    """The undiscounted return of every episode of a dataset."""
    _, index = np.unique(traj.episode_id, return_inverse=True)
    return np.bincount(index, weights=traj.reward.astype(np.float64))


class LocomotionFamily(Family[LocomotionTaskParams]):
    """Hopper, Walker2d and HalfCheetah (gymnasium MuJoCo ``-v5``) with D4RL-recipe datasets regenerated here:
    plans start at the current state, are guided by a learned value and replanned at every step."""

    name = "locomotion"
    conditioning = "start"
    normalizer_kind = "gaussian"
    uses_value_function = True

    def make_simulator(self, task: TaskParams[LocomotionTaskParams] | str) -> LocomotionSimulator:
        """The simulator of a task (or a task name like ``hopper-medium``)."""
        name = getattr(task, "name", task)
        env_id, _ = parse_task_name(name)
        steps = task.settings.episode_steps if isinstance(task, TaskParams) else 1000
        return LocomotionSimulator(env_id, episode_steps=steps)

    def collect(self, task: TaskParams[LocomotionTaskParams], files: TaskFiles, progress: bool) -> Trajectories:
        """Train the behaviour policies (saved under ``models/<task>/collect``; a medium search killed midway goes on
        from ``files.collect_resume``) and record the dataset."""
        from adaptdiffuser.families.locomotion.behaviour import collect_locomotion_dataset

        return collect_locomotion_dataset(task.name, files.collect, task.settings.behaviour, progress,
                                          resume_path=files.collect_resume, resume_tag=files.code)  # fmt: skip

    def reference(self, task: TaskParams[LocomotionTaskParams], files: TaskFiles, progress: bool) -> dict[str, Any]:
        """D4RL's random and expert returns (the score's 0 and 100), and beside them, on the evaluation seeds and
        episode length: our uniform random policy, our medium behaviour policy, and the dataset's episodes."""
        from adaptdiffuser.families.locomotion.behaviour import (
            SUMMARY_FILE,
            evaluate_policy_returns,
            load_behaviour_policy,
            random_policy,
        )

        env_id, _ = parse_task_name(task.name)
        r_min, r_max = REFERENCE_RETURNS[robot_of(env_id)]
        ev, steps = task.evaluate, task.settings.episode_steps
        sim = self.make_simulator(task)
        ref: dict[str, Any] = {"r_min": r_min, "r_max": r_max, "n_episodes": ev.episodes, "source": "d4rl"}
        policies = {"random": random_policy(sim, ev.seed)}
        if (files.collect / SUMMARY_FILE).exists():
            policies["behaviour"] = load_behaviour_policy(files.collect)
            medium = json.loads((files.collect / SUMMARY_FILE).read_text())["medium"]
            ref["behaviour_chosen"] = {key: medium.get(key) for key in ("band", "steps", "normalized_score", "rewinds")}
        else:  # imported data (the import stage): no behaviour policy was trained
            ref["behaviour"] = "none: the task's data was imported, so there is no behaviour policy to score"
        for who, policy in policies.items():
            returns = evaluate_policy_returns(policy, sim, ev.episodes, ev.seed, steps)
            scores = normalized_score(returns, env_id)
            ref[f"{who}_return_mean"] = float(returns.mean())
            ref[f"{who}_score_mean"] = float(np.mean(scores))
            ref[f"{who}_score_stderr"] = standard_error(scores)
        data = episode_returns(read_trajectories(files.dataset, env=task.name))
        data_scores = normalized_score(data, env_id)
        ref["dataset"] = {
            "score_mean": float(np.mean(data_scores)),
            "score_stderr": standard_error(data_scores),
            "return_mean": float(data.mean()),
            "n_episodes": int(len(data)),
        }
        return ref

    def controller(
        self, task: TaskParams[LocomotionTaskParams], planner: Any, files: TaskFiles, device: Any
    ) -> Controller:
        """Diffuser's value-guided controller: N plans from the current state, the first action of the best."""
        from adaptdiffuser.diffusion.guidance import ValueGuidance
        from adaptdiffuser.value_training import load_value

        value_net, _ = load_value(files.value, device)
        g = task.settings.guide
        guidance = ValueGuidance(value_net, g.scale, g.n_guide_steps, g.t_stopgrad, g.scale_grad_by_std)
        return self.value_controller(planner, guidance, g.n_samples, task.evaluate.seed, g.warm_start_step)

    def value_controller(
        self, planner: Any, guidance: Any, n_samples: int, seed: int, warm_start_step: int | None = None
    ) -> Controller:
        """The value-guided controller around ``planner`` and a value ``guidance`` of one's own (the benchmarks
        time it with untrained networks): N plans from the current state, the first action of the best."""
        from adaptdiffuser.families.locomotion.controller import ValuePlanningController

        return ValuePlanningController(planner, guidance, n_samples, seed, warm_start_step)

    def generate(self, task, planner, files, cfg, alpha, seed, generator, progress):
        """Value-guided segments from dataset states and fresh resets (``alpha`` guides maze coins only: unused)."""
        from adaptdiffuser.families.locomotion.evolution import generate_segments

        return generate_segments(self.make_simulator(task), task, planner, files, cfg, seed, generator, progress)

    def discriminate(self, task, generated, cfg, phase, files, progress):
        """Execute each segment's actions from its start state; reject falls and drift; select by real reward."""
        from adaptdiffuser.families.locomotion.evolution import judge_segments

        dataset = read_trajectories(files.dataset, env=task.name)
        return judge_segments(self.make_simulator(task), task, generated, dataset, cfg, phase, progress)

    def selected_data(self, task, generated, judgement, generator):
        from adaptdiffuser.families.locomotion.evolution import selected_segments

        return selected_segments(self.make_simulator(task), task, judgement, generator)

    def from_external(self, task: TaskParams[LocomotionTaskParams], raw: Any) -> Trajectories:
        """D4RL's or Minari's MuJoCo data of the task's robot (``-v5`` dimensions)."""
        from adaptdiffuser.families.locomotion.external import locomotion_trajectories

        return locomotion_trajectories(task, self.make_simulator(task), raw)

    def export_spec(self, task: TaskParams[LocomotionTaskParams]) -> tuple[Any, Any, Any]:
        from adaptdiffuser.families.locomotion.external import locomotion_export_spec

        return locomotion_export_spec(self.make_simulator(task))

    def episode_metrics(self, result: EpisodeBatchResult) -> dict[str, float]:
        return {
            "length_mean": float(np.mean(result.lengths)),
            "terminated_rate": float(np.mean(result.terminated)),
        }

    def save_picture(
        self,
        task: TaskParams[LocomotionTaskParams],
        path: Path,
        plan: np.ndarray | None,
        executed: np.ndarray,
        title: str,
        goal: Any = None,
    ) -> None:
        """The torso height and angle (the first two observation dims) over the episode, and over the first plan."""
        save_series_picture(path, executed, plan, ["torso height", "torso angle"], title)

    def describe(self, task: TaskParams[LocomotionTaskParams]) -> dict[str, Any]:
        env_id, dataset = parse_task_name(task.name)
        return {"env_id": env_id, "dataset": dataset, "episode_steps": task.settings.episode_steps}


FAMILY = LocomotionFamily
