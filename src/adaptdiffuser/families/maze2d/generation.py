"""Generation of synthetic data: batched goal-conditioned plans for many tasks, and trajectories for those tasks
as a dataset in the project's schema, each row saying which task (start, goal) it was made for. The tasks
themselves come from the family, in its folder."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from adaptdiffuser.contract import TrackedTrajectory
from adaptdiffuser.data.schema import SchemaError, Trajectories, make_metadata
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.families.maze2d.gold_coin import CoinObjective
from adaptdiffuser.planning import Planner

TASK_COLUMNS = ("task_id", "task_start", "task_goal")


@dataclass
class NavigationTasks:
    """``n`` start states and goal states (goal velocity zero), the grid cells they were drawn from (empty when
    read back from a file), and optionally coin positions ``[n, 2]`` (NaN rows for tasks without a coin)."""

    starts: np.ndarray
    goals: np.ndarray
    start_cells: np.ndarray
    goal_cells: np.ndarray
    coins: np.ndarray | None = None

    def has_coin(self) -> np.ndarray:
        """Which tasks carry a coin."""
        if self.coins is None:
            return np.zeros(len(self), dtype=bool)
        return ~np.isnan(self.coins).any(axis=1)

    def __len__(self) -> int:
        return len(self.starts)


def generate_plans(
    planner: Planner, tasks: NavigationTasks, batch_size: int, seed: int, alpha: float = 0.0, progress: bool = True
) -> np.ndarray:
    """Plans ``[n_tasks, horizon, act_dim + obs_dim]`` (raw units), one per task, sampled in batches; task ``i``
    uses seed ``(seed, i)``, so its plan depends neither on the batch size nor on what else runs. Tasks with a coin
    are planned in their own batches, guided toward their coin with scale ``alpha``."""
    if batch_size <= 0:
        raise ValueError(f"batch_size must be positive, got {batch_size}")
    plans = np.zeros((len(tasks), planner.horizon, planner.model.transition_dim))
    with_coin = tasks.has_coin()
    batches = [
        (rows[i : i + batch_size], coin)
        for coin, rows in ((False, np.flatnonzero(~with_coin)), (True, np.flatnonzero(with_coin)))
        for i in range(0, len(rows), batch_size)
    ]
    for rows, coin in tqdm(batches, desc="generate", disable=not progress):
        guidance = None
        if coin:
            coins = torch.as_tensor(tasks.coins[rows], dtype=planner.dtype, device=planner.device)
            guidance = planner.guidance(CoinObjective(coins), alpha)
        seeds = [derive_seed(seed, i) for i in rows]
        plans[rows] = planner.plan(tasks.starts[rows], tasks.goals[rows], seeds, guidance=guidance)
    return plans


def task_trajectories(
    trajectories: list[TrackedTrajectory],
    tasks: NavigationTasks,
    task_ids: np.ndarray,
    env: str,
    generator: dict[str, Any],
) -> Trajectories:
    """Trajectories made for tasks as one dataset (``source = synthetic``): ``trajectories[i]`` belongs to task
    ``task_ids[i]``, which each of its rows records in the extra columns ``task_id``, ``task_start``,
    ``task_goal`` and, when the tasks have coins, ``task_coin`` (NaN for tasks without one)."""
    task_ids = np.asarray(task_ids, dtype=np.int64)
    if len(trajectories) == 0:
        raise ValueError("no trajectories; nothing to write")
    if len(trajectories) != len(task_ids):
        raise ValueError(f"{len(trajectories)} trajectories but {len(task_ids)} task ids")
    obs_dim = trajectories[0].observations.shape[1]
    act_dim = trajectories[0].actions.shape[1]
    lengths = [len(t.observations) for t in trajectories]
    n = sum(lengths)
    timeout = np.zeros(n, dtype=bool)
    timeout[np.cumsum(lengths) - 1] = True
    extra = {
        "task_id": np.repeat(task_ids, lengths),
        "task_start": np.repeat(tasks.starts[task_ids], lengths, axis=0).astype(np.float32),
        "task_goal": np.repeat(tasks.goals[task_ids], lengths, axis=0).astype(np.float32),
    }
    if tasks.coins is not None:
        extra["task_coin"] = np.repeat(tasks.coins[task_ids], lengths, axis=0).astype(np.float32)
    return Trajectories(
        episode_id=np.repeat(np.arange(len(trajectories)), lengths),
        step=np.concatenate([np.arange(k) for k in lengths]),
        observation=np.concatenate([t.observations for t in trajectories]),
        action=np.concatenate([t.actions for t in trajectories]),
        reward=np.concatenate([t.rewards for t in trajectories]).astype(np.float32),
        terminal=np.zeros(n, dtype=bool),
        timeout=timeout,
        metadata=make_metadata(env, obs_dim, act_dim, "synthetic", generator),
        extra=extra,
    )


def split_task_trajectories(traj: Trajectories) -> tuple[list[np.ndarray], list[np.ndarray], NavigationTasks]:
    """Inverse of :func:`task_trajectories` for plans: per-episode states ``[H, obs]`` and actions ``[H, act]``
    and the task of each episode (cells are not stored, so they come back empty)."""
    missing = [name for name in TASK_COLUMNS if name not in traj.extra]
    if missing:
        raise SchemaError(f"synthetic trajectory file lacks task column {missing[0]!r}")
    episodes = traj.episodes()
    firsts = np.array([ep.start for ep in episodes], dtype=np.int64)
    tasks = NavigationTasks(
        starts=np.asarray(traj.extra["task_start"], dtype=np.float64)[firsts],
        goals=np.asarray(traj.extra["task_goal"], dtype=np.float64)[firsts],
        start_cells=np.zeros((0, 2), dtype=np.int64),
        goal_cells=np.zeros((0, 2), dtype=np.int64),
        coins=np.asarray(traj.extra["task_coin"], dtype=np.float64)[firsts] if "task_coin" in traj.extra else None,
    )
    states = [traj.observation[ep].astype(np.float64) for ep in episodes]
    actions = [traj.action[ep].astype(np.float64) for ep in episodes]
    return states, actions, tasks
