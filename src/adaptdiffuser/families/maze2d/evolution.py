"""Maze2D's evolution phases: goal-conditioned plans for random (start, goal) cells, a quarter of them guided toward
a gold coin; the discriminator follows each plan with the evaluation's PD follower and keeps plans by the paper's
reward/length rule (or a generic one), and coin plans when the coin was picked before the goal."""

from __future__ import annotations

from functools import partial
from typing import Any

import numpy as np

from adaptdiffuser.config import DiscriminateParams, GenerateParams, TaskParams
from adaptdiffuser.data.schema import Trajectories
from adaptdiffuser.evolution.discriminator import Judgement, discriminate, planned_trajectory
from adaptdiffuser.evolution.generate import generate_plans, split_task_trajectories, task_trajectories
from adaptdiffuser.families.maze2d.execution import PlanFollower
from adaptdiffuser.families.maze2d.selection import picks_coin_then_reaches_goal
from adaptdiffuser.families.maze2d.simulator import Maze2D
from adaptdiffuser.families.maze2d.tasks import add_coins, sample_navigation_tasks
from adaptdiffuser.planning import Planner


def generate_navigation_data(
    env: Maze2D,
    task: TaskParams,
    planner: Planner,
    cfg: GenerateParams,
    alpha: float,
    seed: int,
    generator: dict[str, Any],
    progress: bool,
) -> tuple[Trajectories, dict[str, float]]:
    """One plan per random task, taken at its word (planned states, actions and reward), with the task columns."""
    rng = np.random.default_rng(seed)
    tasks = sample_navigation_tasks(env, cfg.tasks, rng, cfg.cell_spread)
    if cfg.coin_fraction > 0:
        tasks = add_coins(env, tasks, cfg.coin_fraction, rng)
    plans = generate_plans(planner, tasks, cfg.batch_size, seed, alpha=alpha, progress=progress)
    act_dim = planner.act_dim
    planned = [
        planned_trajectory(env, p[:, act_dim:], p[:, :act_dim], goal)
        for p, goal in zip(plans, tasks.goals, strict=True)
    ]
    traj = task_trajectories(planned, tasks, np.arange(len(tasks)), task.name, generator)
    stats = {
        "generated": len(tasks),
        "coin_tasks": int(tasks.has_coin().sum()),
        "planned_reach_rate": float(np.mean([t.steps_to_goal >= 0 for t in planned])),
        "planned_return_mean": float(np.mean([t.total_reward for t in planned])),
    }
    return traj, stats


def judge_navigation_data(
    env: Maze2D, task: TaskParams, generated: Trajectories, cfg: DiscriminateParams, rule: Any, progress: bool
) -> Judgement:
    """Track every plan from its first state with the plan follower; select navigation plans by ``rule`` and coin
    plans that pick their coin and then reach the goal."""
    states, actions, tasks = split_task_trajectories(generated)
    return discriminate(
        env,
        states,
        actions,
        tasks.goals,
        cfg,
        rule,
        PlanFollower,
        coins=tasks.coins,
        coin_check=partial(picks_coin_then_reaches_goal, radius=task.settings.gold_coin.radius),
        progress=progress,
    )


def selected_navigation_data(
    task: TaskParams, generated: Trajectories, judgement: Judgement, generator: dict[str, Any]
) -> Trajectories:
    """The kept executed trajectories, each row naming its task."""
    _, _, tasks = split_task_trajectories(generated)
    kept = [judgement.trajectories[i] for i in judgement.kept]
    return task_trajectories(kept, tasks, judgement.kept, task.name, generator)
