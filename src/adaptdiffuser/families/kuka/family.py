"""The KUKA family as the generic pipeline sees it (registered in ``family_registry.py``): the model learns block
stacking from the scripted demonstrator's states; stacking is evaluated as the task's score and pick-and-place (the
unseen task, guided) beside it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from adaptdiffuser.config import TaskParams
from adaptdiffuser.contract import Controller, EpisodeBatchResult, Family, TaskFiles
from adaptdiffuser.data.schema import Trajectories
from adaptdiffuser.evaluation import RandomController, normalized_score, run_episodes, standard_error
from adaptdiffuser.families.kuka.params import KukaTaskParams
from adaptdiffuser.families.kuka.scene import FLAG_COLUMNS, N_BLOCKS
from adaptdiffuser.families.kuka.simulator import KukaSimulator

#: pick-and-place setups: 1 = blocks scattered on the floor, 2 = blocks start in one tower (the paper's two)
SETUP_LAYOUTS = {1: "scattered", 2: "tower"}


def episode_steps(task: TaskParams[KukaTaskParams], replans: int) -> int:
    """An episode is ``replans`` open-loop plans of the horizon (each plan's first state is the current one)."""
    return replans * (task.diffusion.horizon - 1)


class KukaFamily(Family[KukaTaskParams]):
    """A KUKA iiwa arm with a suction cup and four blocks (PyBullet); plans are 39-d states (no actions), executed
    open loop by position control and replanned a few times per episode."""

    name = "kuka"
    conditioning = "start"
    normalizer_kind = "minmax"
    unseen_task = KukaTaskParams.UNSEEN_TASK

    def make_simulator(self, task: TaskParams[KukaTaskParams], kind: str = "stacking", setup: int = 1) -> KukaSimulator:
        """The simulator of stacking (the task's score) or of pick-and-place setup ``setup``."""
        s = task.settings
        replans = s.pick_place.replans if kind == "pick_place" else s.replans
        return KukaSimulator(s, kind, SETUP_LAYOUTS[setup], episode_steps(task, replans))

    def collect(self, task: TaskParams[KukaTaskParams], files: TaskFiles, progress: bool) -> Trajectories:
        """Scripted stacking demonstrations; the demonstrator's own figures go to ``demonstrator.json``."""
        from adaptdiffuser.families.kuka.demonstrator import collect_demonstrations
        from adaptdiffuser.io import write_json

        traj, figures = collect_demonstrations(self.make_simulator(task), task.settings, task.name, progress)
        write_json(files.collect / "demonstrator.json", figures)
        return traj

    def reference(self, task: TaskParams[KukaTaskParams], files: TaskFiles, progress: bool) -> dict[str, Any]:
        """Score 0 = nothing stacked, 100 = the full tower (3 blocks on others); beside it, on the evaluation seeds,
        the scripted demonstrator and uniformly random joint targets and suction flags."""
        from adaptdiffuser.families.kuka.demonstrator import DemonstratorController

        ev, d = task.evaluate, task.settings.demonstrator
        ref: dict[str, Any] = {"r_min": 0.0, "r_max": float(N_BLOCKS - 1), "n_episodes": ev.episodes}
        controllers = {
            "demonstrator": DemonstratorController(
                d.speed, d.safe_height, d.dwell, ev.seed if d.order == "shuffled" else None
            ),
            "random": RandomController(ev.seed),
        }
        for who, controller in controllers.items():
            result = run_episodes(
                lambda: self.make_simulator(task),
                controller,
                ev.episodes,
                ev.seed,
                ev.batch_size,
                desc=f"reference {who}",
                progress=progress,
            )
            scores = normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"])
            ref[f"{who}_score_mean"] = float(np.mean(scores))
            ref[f"{who}_score_stderr"] = standard_error(scores)
        return ref

    def controller(self, task: TaskParams[KukaTaskParams], planner: Any, files: TaskFiles, device: Any) -> Controller:
        """Open-loop plans of the horizon, ``replans`` per episode (or replanned more often, per ``planning``)."""
        from adaptdiffuser.families.kuka.execution import task_controller

        return task_controller(task, planner, task.evaluate.seed)

    def pick_place_episodes(
        self,
        task: TaskParams[KukaTaskParams],
        planner: Any,
        alpha: float,
        setup: int,
        record: bool = False,
        progress: bool = False,
    ) -> tuple[EpisodeBatchResult, Controller]:
        """The pick-and-place evaluation episodes of one setup (``pick_place`` settings), guided with scale
        ``alpha``; with the controller that ran them (its ``recorded`` plans when ``record``)."""
        from adaptdiffuser.families.kuka.execution import pick_place_controller

        p = task.settings.pick_place
        controller = pick_place_controller(task, planner, alpha, p.seed, record)
        result = run_episodes(
            lambda: self.make_simulator(task, "pick_place", setup),
            controller,
            p.episodes,
            p.seed,
            p.batch_size,
            desc=f"pick-and-place setup {setup}",
            progress=progress,
        )
        return result, controller

    def evaluate_unseen(self, task, planner, alpha, ref, pictures, title, progress):
        """Pick-and-place (no demonstrations) in each setup of ``pick_place.setups``, guided with scale ``alpha``:
        score = blocks placed / 4 x 100, over all episodes (``score_*``) and per setup (``setup<k>_score_*``). No
        pictures."""
        metrics: dict[str, float] = {}
        every: list[np.ndarray] = []
        for setup in task.settings.pick_place.setups:
            result, _ = self.pick_place_episodes(task, planner, alpha, setup, progress=progress)
            scores = normalized_score(np.asarray(result.returns), 0.0, float(N_BLOCKS))
            metrics[f"setup{setup}_score_mean"] = float(np.mean(scores))
            metrics[f"setup{setup}_score_stderr"] = standard_error(scores)
            every.append(scores)
        scores = np.concatenate(every)
        return {"score_mean": float(np.mean(scores)), "score_stderr": standard_error(scores),
                "n_episodes": int(len(scores)), **metrics}  # fmt: skip

    def unseen_objective(self, metrics: dict[str, Any]) -> float:
        """The pick-and-place score over every setup's episodes."""
        return float(metrics["score_mean"])

    def generate(self, task, planner, files, cfg, alpha, seed, generator, progress):
        """Pick-and-place episodes from both setups, guided with scale ``alpha`` (as the unseen evaluation)."""
        from adaptdiffuser.families.kuka.evolution import generate_episodes

        return generate_episodes(self.make_simulator, task, planner, cfg, alpha, seed, generator, progress)

    def discriminate(self, task, generated, cfg, phase, files, progress):
        """Execute each episode's plans; reject those that leave the plan (joints and flags, or blocks where the arm
        follows them) and states outside the stacking data's range; select by blocks placed."""
        from adaptdiffuser.data.schema import read_trajectories
        from adaptdiffuser.families.kuka.evolution import judge_episodes

        expert = read_trajectories(files.dataset, task.name).observation
        excess = task.settings.selection.max_range_excess
        return judge_episodes(self.make_simulator, task, generated, cfg, expert, excess, progress)

    def selected_data(self, task, generated, judgement, generator):
        from adaptdiffuser.families.kuka.evolution import selected_episodes

        return selected_episodes(task, judgement, generator)

    def episode_metrics(self, result: EpisodeBatchResult) -> dict[str, float]:
        """The share of full towers, and how many blocks the cup held at some step of an episode (mean): whether
        the plans reach the real blocks at all."""
        full = np.asarray(result.returns) >= N_BLOCKS - 1
        held = [int((np.asarray(e)[:, list(FLAG_COLUMNS)] > 0.5).any(axis=0).sum()) for e in result.executed]
        return {"full_tower_rate": float(np.mean(full)), "blocks_held_mean": float(np.mean(held))}

    def save_picture(
        self,
        task: TaskParams[KukaTaskParams],
        path: Path,
        plan: np.ndarray | None,
        executed: np.ndarray,
        title: str,
        goal: Any = None,
    ) -> None:
        """The final scene (rebuilt at the last executed state and rendered) and the blocks' heights."""
        from adaptdiffuser.families.kuka.pictures import save_episode_picture

        sim = self.make_simulator(task)
        sim.set_state(executed[-1])
        save_episode_picture(path, sim.render(), executed, plan, title)
        sim.close()

    def describe(self, task: TaskParams[KukaTaskParams]) -> dict[str, Any]:
        return {
            "simulator": "pybullet kuka_iiwa, 4 blocks, suction",
            "stacking_episode_steps": episode_steps(task, task.settings.replans),
        }


FAMILY = KukaFamily
