"""The Maze2D family as the generic pipeline sees it (registered in ``family_registry.py``)."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from adaptdiffuser.config import DiscriminateParams, TaskParams
from adaptdiffuser.contract import Controller, EpisodeBatchResult, Family, TaskFiles
from adaptdiffuser.data.schema import Trajectories, make_metadata
from adaptdiffuser.evaluation import RandomController, run_episodes, standard_error
from adaptdiffuser.families.maze2d.expert import ExpertController, collect_expert_stream
from adaptdiffuser.families.maze2d.params import Maze2DTaskParams
from adaptdiffuser.families.maze2d.simulator import Maze2D, resolve_layout
from adaptdiffuser.plots import save_plan_picture

if TYPE_CHECKING:
    from adaptdiffuser.evolution.discriminator import SelectionRule

# D4RL's reference returns (raw grid coordinates, their expert), for comparison only.
D4RL_REFERENCE = {"umaze": (23.85, 161.86), "medium": (13.13, 277.39), "large": (6.7, 273.99)}


class Maze2DFamily(Family[Maze2DTaskParams]):
    """Point-mass navigation: plans inpaint the start and the goal, and a PD controller follows the planned states."""

    name = "maze2d"
    conditioning = "start_goal"
    normalizer_kind = "minmax"
    unseen_task = Maze2DTaskParams.UNSEEN_TASK

    def make_simulator(self, task: TaskParams[Maze2DTaskParams]) -> Maze2D:
        """A fresh simulator: protocol from ``env``, expert gains from ``expert``, plan-follower gains from
        ``follower``."""
        e, x, f = task.settings.env, task.settings.expert, task.settings.follower
        return Maze2D(
            resolve_layout(e.maze, e.layout),
            name=task.settings.maze_name,
            episode_steps=e.episode_steps,
            goal_radius=e.goal_radius,
            reset_pos_noise=e.reset_pos_noise,
            reset_vel_noise=e.reset_vel_noise,
            random_goal=e.random_goal,
            expert_p_gain=x.p_gain,
            expert_d_gain=x.d_gain,
            expert_jitter=x.jitter,
            expert_waypoint_radius=x.waypoint_radius,
            tracking_p_gain=f.p_gain,
            tracking_d_gain=f.d_gain,
        )

    def collect(self, task: TaskParams[Maze2DTaskParams], files: TaskFiles, progress: bool) -> Trajectories:
        """D4RL's waypoint expert as one stream of ``collect.steps`` steps, cut into episodes at each new goal."""
        env = self.make_simulator(task)
        c = task.settings.collect
        traj = collect_expert_stream(env, c.steps, c.seed, progress=progress)
        traj.metadata = make_metadata(
            env=task.name,
            obs_dim=env.obs_dim,
            act_dim=env.act_dim,
            source="expert",
            generator={
                "recipe": "d4rl-waypoint-stream",
                "collect": asdict(c),
                "expert": asdict(task.settings.expert),
                "env": asdict(task.settings.env),
            },
        )
        return traj

    def reference(self, task: TaskParams[Maze2DTaskParams], files: TaskFiles, progress: bool) -> dict[str, Any]:
        """R_min (uniform random actions) and R_max (the waypoint expert) under the protocol, on the evaluation
        seeds; D4RL's own figures beside them for the standard mazes."""
        ev = task.evaluate

        def run(controller: Controller, who: str) -> EpisodeBatchResult:
            return run_episodes(lambda: self.make_simulator(task), controller, ev.episodes, ev.seed, ev.batch_size,
                                desc=f"reference: {who}", progress=progress)  # fmt: skip

        random, expert = run(RandomController(ev.seed), "random"), run(ExpertController(ev.seed), "expert")
        ref: dict[str, Any] = {
            "r_min": float(np.mean(random.returns)),
            "r_max": float(np.mean(expert.returns)),
            "r_min_stderr": standard_error(random.returns),
            "r_max_stderr": standard_error(expert.returns),
            "n_episodes": ev.episodes,
            "expert_success_rate": float(np.mean(expert.final_success)),
        }
        e = task.settings.env
        if e.layout is None and e.maze in D4RL_REFERENCE:
            ref["d4rl_r_min"], ref["d4rl_r_max"] = D4RL_REFERENCE[e.maze]
        return ref

    def controller(self, task: TaskParams[Maze2DTaskParams], planner: Any, files: TaskFiles, device: Any) -> Controller:
        from adaptdiffuser.families.maze2d.execution import PlannerController

        return PlannerController(planner, task.evaluate.seed, task.planner.replan_every)

    def evaluate_unseen(self, task, planner, alpha, ref, pictures, title, progress):
        """The gold-coin task (:func:`~adaptdiffuser.families.maze2d.gold_coin.evaluate_gold_coin`)."""
        from adaptdiffuser.families.maze2d.gold_coin import evaluate_gold_coin

        make_env = lambda: self.make_simulator(task)  # noqa: E731
        return evaluate_gold_coin(make_env, task, planner, alpha, ref, pictures, title, progress)

    def unseen_objective(self, metrics: dict[str, Any]) -> float:
        """100 x the share of cases that pick the coin and reach the goal."""
        return 100.0 * float(metrics["both_rate"])

    def selection_rule(
        self, task: TaskParams[Maze2DTaskParams], cfg: DiscriminateParams, recipe: str = "plans"
    ) -> SelectionRule:
        """The discriminator's rule for the navigation tasks of ``task``'s evolution: under ``rule: paper`` the
        appendix's thresholds for its maze, else the generic rule ``cfg.rule`` names; for data made by the
        ``rollouts`` recipe, among the rollouts that reach their goal on their real length (``RolloutRule``), the
        paper rule's return clause alone (``PaperReturnClause``: the shorter paths) or that generic rule."""
        from adaptdiffuser.evolution.discriminator import generic_selection_rule
        from adaptdiffuser.families.maze2d.selection import PAPER_MAZE_RULES, PaperReturnClause, RolloutRule

        paper = cfg.rule == "paper"
        rule = PAPER_MAZE_RULES[task.settings.env.maze] if paper else generic_selection_rule(cfg)
        if recipe == "rollouts":
            inner = PaperReturnClause(rule.episode_steps, rule.min_score) if paper else rule
            return RolloutRule(inner, task.settings.episode_steps, rank_by_episode_return=not paper)
        return rule

    def generate(self, task, planner, files, cfg, alpha, seed, generator, progress):
        """Plans (or, with ``evolution.generate.recipe: rollouts``, closed-loop rollouts) for random (start, goal)
        cells, ``evolution.coin_fraction`` of them guided toward a coin (``alpha``)."""
        from adaptdiffuser.families.maze2d.evolution import generate_navigation_data

        env = self.make_simulator(task)
        return generate_navigation_data(env, task, planner, cfg, alpha, seed, generator, progress)

    def discriminate(self, task, generated, cfg, phase, files, progress):
        """Follow every plan with the PD follower (rollouts were executed already); the paper's rule (or a generic
        one) on real reward and length."""
        from adaptdiffuser.families.maze2d.evolution import generated_recipe, judge_navigation_data

        env = self.make_simulator(task)
        rule = self.selection_rule(task, cfg, generated_recipe(generated))
        return judge_navigation_data(env, task, generated, cfg, rule, progress)

    def selected_data(self, task, generated, judgement, generator):
        from adaptdiffuser.families.maze2d.evolution import selected_navigation_data

        return selected_navigation_data(task, generated, judgement, generator)

    def episode_columns(self, result: EpisodeBatchResult) -> dict[str, list[Any]]:
        return {
            "start_x": [s[0] for s in result.starts],
            "start_y": [s[1] for s in result.starts],
            "goal_x": [g[0] for g in result.goals],
            "goal_y": [g[1] for g in result.goals],
            "final_success": result.final_success,
            "first_goal_step": result.first_goal_step,
        }

    def episode_metrics(self, result: EpisodeBatchResult) -> dict[str, float]:
        return {"success_rate": float(np.mean(result.final_success))}

    def save_picture(
        self,
        task: TaskParams[Maze2DTaskParams],
        path: Path,
        plan: np.ndarray | None,
        executed: np.ndarray,
        title: str,
        goal: Any = None,
    ) -> None:
        save_plan_picture(self.make_simulator(task), path, plan, executed, title, goal=goal)

    def describe(self, task: TaskParams[Maze2DTaskParams]) -> dict[str, Any]:
        return {"maze": task.settings.maze_name, "episode_steps": task.settings.episode_steps}

    def from_external(self, task: TaskParams[Maze2DTaskParams], raw: Any) -> Trajectories:
        """D4RL's Maze2D files (converted from D4RL's coordinates) or Minari's PointMaze datasets."""
        from adaptdiffuser.families.maze2d.external import maze_trajectories

        return maze_trajectories(task, self.make_simulator(task), raw)

    def export_spec(self, task: TaskParams[Maze2DTaskParams]) -> tuple[Any, Any, Any]:
        from adaptdiffuser.families.maze2d.external import maze_export_spec

        return maze_export_spec(task, self.make_simulator(task))


FAMILY = Maze2DFamily
