"""Generation of synthetic data: batched goal-conditioned plans for many tasks, and the kept (executed)
trajectories as a dataset in the project's schema, with the task each one was made for."""

from __future__ import annotations

from typing import Any

import numpy as np
from tqdm import tqdm

from adaptdiffuser.data.schema import Trajectories, make_metadata
from adaptdiffuser.evolution.discriminator import TrackedTrajectory
from adaptdiffuser.evolution.tasks import NavigationTasks
from adaptdiffuser.planning import Planner


def generate_plans(
    planner: Planner, tasks: NavigationTasks, batch_size: int, seed: int, progress: bool = True
) -> np.ndarray:
    """Plans ``[n_tasks, horizon, act_dim + obs_dim]`` (raw units), one per task, sampled in batches; batch
    ``b`` uses seed ``(seed, b)`` so the result does not depend on what else runs."""
    if batch_size <= 0:
        raise ValueError(f"batch_size must be positive, got {batch_size}")
    plans = []
    for b, first in enumerate(tqdm(range(0, len(tasks), batch_size), desc="generate", disable=not progress)):
        rows = slice(first, first + batch_size)
        batch_seed = int(np.random.SeedSequence([seed, b]).generate_state(1)[0])
        plans.append(planner.plan(tasks.starts[rows], tasks.goals[rows], seed=batch_seed))
    return np.concatenate(plans)


def synthetic_trajectories(
    tracked: list[TrackedTrajectory], tasks: NavigationTasks, keep: np.ndarray, env: str, generator: dict[str, Any]
) -> Trajectories:
    """The kept executed trajectories as one dataset (``source = synthetic``); each row carries its task in the
    extra columns ``task_id``, ``task_start`` and ``task_goal``."""
    keep = np.asarray(keep, dtype=np.int64)
    if keep.size == 0:
        raise ValueError("no trajectory was kept; nothing to write")
    parts = [tracked[i] for i in keep]
    obs_dim = parts[0].observations.shape[1]
    act_dim = parts[0].actions.shape[1]
    lengths = [len(p.observations) for p in parts]
    n = sum(lengths)
    episode_id = np.repeat(np.arange(len(parts)), lengths)
    timeout = np.zeros(n, dtype=bool)
    timeout[np.cumsum(lengths) - 1] = True
    return Trajectories(
        episode_id=episode_id,
        step=np.concatenate([np.arange(k) for k in lengths]),
        observation=np.concatenate([p.observations for p in parts]),
        action=np.concatenate([p.actions for p in parts]),
        reward=np.concatenate([p.rewards for p in parts]).astype(np.float32),
        terminal=np.zeros(n, dtype=bool),
        timeout=timeout,
        metadata=make_metadata(env, obs_dim, act_dim, "synthetic", generator),
        extra={
            "task_id": np.repeat(keep, lengths),
            "task_start": np.repeat(tasks.starts[keep], lengths, axis=0).astype(np.float32),
            "task_goal": np.repeat(tasks.goals[keep], lengths, axis=0).astype(np.float32),
        },
    )
