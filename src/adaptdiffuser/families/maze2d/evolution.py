"""Maze2D's evolution phases: goal-conditioned plans for random (start, goal) cells, a quarter of them guided toward
a gold coin; the discriminator follows each plan with the evaluation's PD follower and keeps plans by the paper's
reward/length rule (or a generic one), and coin plans when the coin was picked before the goal.

``evolution.generate.recipe`` chooses how: ``plans`` (one open-loop plan of the horizon per task, tracked by the
discriminator) or ``rollouts`` (closed-loop rollouts that replan and end at the goal, see :mod:`.rollouts`, judged
as executed with their real length).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from adaptdiffuser.config import DiscriminateParams, GenerateParams, TaskParams
from adaptdiffuser.contract import Judgement, TrackedTrajectory
from adaptdiffuser.data.schema import Trajectories
from adaptdiffuser.evolution.discriminator import SelectionRule, discriminate, planned_trajectory
from adaptdiffuser.families.maze2d.execution import PlanFollower
from adaptdiffuser.families.maze2d.generation import (
    NavigationTasks,
    generate_plans,
    split_task_trajectories,
    task_trajectories,
)
from adaptdiffuser.families.maze2d.params import EvolutionSettings, Maze2DTaskParams
from adaptdiffuser.families.maze2d.rollouts import (
    ERROR_COLUMN,
    reached_goal,
    real_length,
    run_rollouts,
    settle_at_goal,
)
from adaptdiffuser.families.maze2d.selection import picks_coin_then_reaches_goal
from adaptdiffuser.families.maze2d.simulator import Maze2D
from adaptdiffuser.families.maze2d.tasks import add_coins, sample_navigation_tasks
from adaptdiffuser.planning import Planner


def generate_navigation_data(
    env: Maze2D,
    task: TaskParams[Maze2DTaskParams],
    planner: Planner,
    cfg: GenerateParams,
    alpha: float,
    seed: int,
    generator: dict[str, Any],
    progress: bool,
) -> tuple[Trajectories, dict[str, float]]:
    """One plan per random task, taken at its word (planned states, actions and reward), with the task columns; or,
    with ``cfg.recipe: rollouts``, one closed-loop rollout per task (:func:`generate_rollout_data`)."""
    tasks = generation_tasks(env, task.settings.evolution, cfg.tasks, seed)
    generator = {**generator, "recipe": cfg.recipe}  # how the discriminator reads them
    if cfg.recipe == "rollouts":
        return generate_rollout_data(env, task, planner, tasks, cfg, alpha, seed, generator, progress)
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


def generated_recipe(generated: Trajectories) -> str:
    """The recipe (``evolution.generate.recipe``) that made a phase's generated data, from its metadata (data
    without it: ``rollouts`` if they carry executed tracking errors, else ``plans``)."""
    default = "rollouts" if ERROR_COLUMN in generated.extra else "plans"
    return str(generated.metadata.get("generator", {}).get("recipe", default))


def generation_tasks(env: Maze2D, settings: EvolutionSettings, n: int, seed: int) -> NavigationTasks:
    """The phase's ``n`` random (start, goal) tasks, the start within ``settings.cell_spread`` of its cell centre,
    the last ``settings.coin_fraction`` of them with a coin."""
    rng = np.random.default_rng(seed)
    tasks = sample_navigation_tasks(env, n, rng, settings.cell_spread)
    if settings.coin_fraction > 0:
        tasks = add_coins(env, tasks, settings.coin_fraction, rng)
    return tasks


def generate_rollout_data(
    env: Maze2D,
    task: TaskParams[Maze2DTaskParams],
    planner: Planner,
    tasks: NavigationTasks,
    cfg: GenerateParams,
    alpha: float,
    seed: int,
    generator: dict[str, Any],
    progress: bool,
) -> tuple[Trajectories, dict[str, float]]:
    """One closed-loop rollout per task in fresh simulators like ``env`` (replanning every
    ``cfg.replan_every`` steps, ending at the goal or after the episode length): the executed states, actions
    and rewards, unpadded, with the task columns and each step's tracking error (column ``tracking_error``)."""
    from adaptdiffuser.family_registry import get_family

    family = get_family(task.family)
    rollouts = run_rollouts(
        lambda: family.make_simulator(task),
        planner,
        tasks,
        seed,
        cfg.replan_every,
        env.episode_steps,
        cfg.batch_size,
        alpha=alpha,
        coin_radius=task.settings.gold_coin.radius,
        progress=progress,
    )
    traj = task_trajectories(rollouts, tasks, np.arange(len(tasks)), task.name, generator)
    traj.extra[ERROR_COLUMN] = np.concatenate([np.concatenate([[0.0], r.errors]) for r in rollouts]).astype(np.float32)
    reached = np.array([reached_goal(r) for r in rollouts])
    lengths = np.array([real_length(r) for r in rollouts])
    stats = {
        "generated": len(tasks),
        "coin_tasks": int(tasks.has_coin().sum()),
        "rollout_reach_rate": float(reached.mean()),
        "rollout_length_mean": float(lengths.mean()),
        "rollout_length_reached_mean": float(lengths[reached].mean()) if reached.any() else -1.0,
        "rollout_steps": int(sum(len(r.observations) - 1 for r in rollouts)),
    }
    return traj, stats


def judge_navigation_data(
    env: Maze2D,
    task: TaskParams[Maze2DTaskParams],
    generated: Trajectories,
    cfg: DiscriminateParams,
    rule: Any,
    progress: bool,
) -> Judgement:
    """Track every plan from its first state with the plan follower; select navigation plans by ``rule`` and coin
    plans that pick their coin and then reach the goal. Rollouts are judged as executed
    (:func:`judge_rollouts`)."""
    if generated_recipe(generated) == "rollouts":
        return judge_rollouts(env, task, generated, cfg, rule)
    states, actions, tasks = split_task_trajectories(generated)
    coin = tasks.has_coin()
    judgement = discriminate(env, states, actions, tasks.goals, cfg, rule, PlanFollower, ~coin, progress)
    return with_coin_tasks(judgement, tasks, task.settings.gold_coin.radius, must_end_at_goal=False)


def with_coin_tasks(judgement: Judgement, tasks: NavigationTasks, radius: float, must_end_at_goal: bool) -> Judgement:
    """``judgement`` (of the navigation tasks) keeping also the coin tasks that passed tracking, picked their coin
    (within ``radius``) before reaching the goal and, with ``must_end_at_goal``, end at the goal; its report gains
    ``coin_generated`` and ``coin_kept``."""
    coin = tasks.has_coin()
    picked = [
        i
        for i in np.flatnonzero(coin & judgement.passed_tracking)
        if picks_coin_then_reaches_goal(judgement.trajectories[i], tasks.coins[i], radius)
        and (reached_goal(judgement.trajectories[i]) or not must_end_at_goal)
    ]
    kept = np.concatenate([judgement.kept, np.asarray(picked, dtype=np.int64)])
    return replace(judgement, kept=kept, details={"coin_generated": int(coin.sum()), "coin_kept": len(picked)})


def rollout_trajectory(
    env: Maze2D, states: np.ndarray, actions: np.ndarray, goal: np.ndarray, errors: np.ndarray | None
) -> TrackedTrajectory:
    """A generated rollout as the discriminator sees it: its states and actions, the protocol's reward of each state
    for its own ``goal``, and its per-step tracking errors (zeros when the file has none)."""
    scored = planned_trajectory(env, states, actions, goal)  # the states' rewards, zero errors
    return scored if errors is None else replace(scored, errors=np.asarray(errors, dtype=np.float64)[1:])


def judge_rollouts(
    env: Maze2D,
    task: TaskParams[Maze2DTaskParams],
    generated: Trajectories,
    cfg: DiscriminateParams,
    rule: SelectionRule,
) -> Judgement:
    """Rollouts were executed as they were made, so every one "tracks": each is scored by the protocol's reward
    of its states (against its own goal) and its real length (:func:`real_length`); navigation rollouts are kept
    by ``rule`` (a :class:`~adaptdiffuser.families.maze2d.selection.RolloutRule`), coin rollouts when they pick
    their coin and then reach the goal."""
    if not cfg.tracking:
        raise ValueError("rollouts are executed as they are made: evolution.discriminate.tracking must be true")
    states, actions, tasks = split_task_trajectories(generated)
    errors = generated.extra.get(ERROR_COLUMN)
    judged = [
        rollout_trajectory(env, s, a, goal, None if errors is None else errors[ep])
        for ep, s, a, goal in zip(generated.episodes(), states, actions, tasks.goals, strict=True)
    ]
    nav = np.flatnonzero(~tasks.has_coin())
    returns = np.array([judged[i].total_reward for i in nav])
    kept = nav[rule.select(returns, np.array([real_length(judged[i]) for i in nav], dtype=np.int64))]
    judgement = Judgement(trajectories=judged, passed_tracking=np.ones(len(judged), dtype=bool), kept=kept)
    return with_coin_tasks(judgement, tasks, task.settings.gold_coin.radius, must_end_at_goal=True)


def arrival_step(trajectory: TrackedTrajectory, coin: np.ndarray | None, radius: float) -> int:
    """The first state at the goal (for a coin task, at or after the first state within ``radius`` of the coin);
    -1 if there is none."""
    first = 0
    if coin is not None and not np.isnan(coin).any():
        near = np.flatnonzero(np.linalg.norm(trajectory.observations[:, :2] - coin[None, :2], axis=1) <= radius)
        if not len(near):
            return -1
        first = int(near[0])
    hits = np.flatnonzero(trajectory.rewards[first:] > 0)
    return first + int(hits[0]) if len(hits) else -1


def stay_after_arrival(trajectory: TrackedTrajectory, coin: np.ndarray | None, radius: float) -> TrackedTrajectory:
    """A kept plan's trajectory cut where it arrives at the goal (:func:`arrival_step`), at rest there for the rest
    of its length; unchanged if it never arrives."""
    stop = arrival_step(trajectory, coin, radius)
    return trajectory if stop < 0 else settle_at_goal(trajectory, stop, len(trajectory.observations))


def selected_navigation_data(
    task: TaskParams[Maze2DTaskParams], generated: Trajectories, judgement: Judgement, generator: dict[str, Any]
) -> Trajectories:
    """The kept executed trajectories, each row naming its task. Kept rollouts (all of them end at the goal) go on
    at rest at the goal for a horizon less one state, so every step of a rollout starts a training window that
    reaches the goal and stays; with ``evolution.stay_at_goal``, kept plans are cut where they arrive at the goal
    and stay there for the rest of the horizon."""
    _, _, tasks = split_task_trajectories(generated)
    kept = [judgement.trajectories[i] for i in judgement.kept]
    h = task.diffusion.horizon
    if generated_recipe(generated) == "rollouts":
        kept = [settle_at_goal(t, len(t.observations) - 1, len(t.observations) + h - 1) for t in kept]
    elif task.settings.evolution.stay_at_goal:
        coins = tasks.coins[judgement.kept] if tasks.coins is not None else [None] * len(kept)
        radius = task.settings.gold_coin.radius
        kept = [stay_after_arrival(t, c, radius) for t, c in zip(kept, coins, strict=True)]
    return task_trajectories(kept, tasks, judgement.kept, task.name, generator)
