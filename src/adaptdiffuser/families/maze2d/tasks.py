"""Synthetic Maze2D tasks for the evolution's generation: random start and goal cells, with random positions inside
the start cell, and optionally a gold coin to pick up on the way (in a third random cell)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from adaptdiffuser.families.maze2d.generation import NavigationTasks
from adaptdiffuser.families.maze2d.simulator import Maze2D


def sample_navigation_tasks(env: Maze2D, n: int, rng: np.random.Generator, cell_spread: float = 0.4) -> NavigationTasks:
    """Draw ``n`` tasks: distinct random start and goal cells; the start is placed uniformly within
    ``cell_spread`` of its cell centre with a small random velocity, the goal at its cell centre."""
    if n <= 0:
        raise ValueError(f"number of tasks must be positive, got {n}")
    free = env.layout.free_cells
    start_idx = rng.integers(len(free), size=n)
    goal_idx = (start_idx + rng.integers(1, len(free), size=n)) % len(free)  # never the start cell
    start_cells = np.array([free[i] for i in start_idx])
    goal_cells = np.array([free[i] for i in goal_idx])
    start_xy = np.stack([env.cell_to_xy(tuple(c)) for c in start_cells]) + rng.uniform(
        -cell_spread, cell_spread, size=(n, 2)
    )
    start_v = rng.normal(0.0, env.reset_vel_noise, size=(n, 2))
    goal_xy = np.stack([env.cell_to_xy(tuple(c)) for c in goal_cells])
    return NavigationTasks(
        starts=np.concatenate([start_xy, start_v], axis=1),
        goals=np.concatenate([goal_xy, np.zeros((n, 2))], axis=1),
        start_cells=start_cells,
        goal_cells=goal_cells,
    )


def add_coins(env: Maze2D, tasks: NavigationTasks, fraction: float, rng: np.random.Generator) -> NavigationTasks:
    """``tasks`` with a coin at the centre of a random free cell (not the start's or the goal's) in the last
    ``round(fraction * n)`` tasks; the others get NaN coins."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"coin fraction must be in [0, 1], got {fraction}")
    coins = np.full((len(tasks), 2), np.nan)
    free = [tuple(c) for c in env.layout.free_cells]
    for i in range(len(tasks) - round(fraction * len(tasks)), len(tasks)):
        taken = {tuple(tasks.start_cells[i]), tuple(tasks.goal_cells[i])}
        options = [c for c in free if c not in taken]
        coins[i] = env.cell_to_xy(options[rng.integers(len(options))])
    return replace(tasks, coins=coins)
