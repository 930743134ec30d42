"""Maze2D data from outside: D4RL's files (their own coordinates) and Minari's PointMaze datasets, as a task's dataset.

D4RL's Maze2D puts cell (row, col) at x = row, y = col (cell centres at integers); gymnasium-robotics (ours, and
Minari's PointMaze datasets) at x = col + 0.5 - width / 2, y = height / 2 - (row + 0.5). So a D4RL position
(x_d, y_d) is ours at x = y_d + 0.5 - width / 2, y = height / 2 - 0.5 - x_d, and velocities and forces turn the
same way: (vx, vy) = (vy_d, -vx_d), (ax, ay) = (ay_d, -ax_d).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from adaptdiffuser.data.d4rl import ExternalData
from adaptdiffuser.data.schema import Trajectories
from adaptdiffuser.families.maze2d.layouts import Layout
from adaptdiffuser.families.maze2d.simulator import Maze2D

#: the largest share of positions allowed in walls or outside the maze (the point never enters a wall)
MAX_OFF_MAZE = 0.01


def d4rl_position_to_xy(layout: Layout, pos: np.ndarray) -> np.ndarray:
    """D4RL positions (x = row, y = col) in gymnasium-robotics coordinates."""
    pos = np.asarray(pos, dtype=np.float64)
    return np.stack([pos[..., 1] + 0.5 - layout.width / 2, layout.height / 2 - 0.5 - pos[..., 0]], axis=-1)


def xy_to_d4rl_position(layout: Layout, xy: np.ndarray) -> np.ndarray:
    """Gymnasium-robotics positions in D4RL's coordinates (the inverse of :func:`d4rl_position_to_xy`)."""
    xy = np.asarray(xy, dtype=np.float64)
    return np.stack([layout.height / 2 - 0.5 - xy[..., 1], xy[..., 0] - 0.5 + layout.width / 2], axis=-1)


def d4rl_vector_to_xy(vec: np.ndarray) -> np.ndarray:
    """A D4RL velocity or force (along row, col) in gymnasium-robotics axes: (v_col, -v_row)."""
    vec = np.asarray(vec, dtype=np.float64)
    return np.stack([vec[..., 1], -vec[..., 0]], axis=-1)


def xy_vector_to_d4rl(vec: np.ndarray) -> np.ndarray:
    """The inverse of :func:`d4rl_vector_to_xy`."""
    vec = np.asarray(vec, dtype=np.float64)
    return np.stack([-vec[..., 1], vec[..., 0]], axis=-1)


def d4rl_observation_to_ours(layout: Layout, obs: np.ndarray) -> np.ndarray:
    """D4RL observations (x, y, vx, vy) as ours."""
    return np.concatenate([d4rl_position_to_xy(layout, obs[:, :2]), d4rl_vector_to_xy(obs[:, 2:4])], axis=1)


def our_observation_to_d4rl(layout: Layout, obs: np.ndarray) -> np.ndarray:
    """Our observations (x, y, vx, vy) in D4RL's coordinates."""
    return np.concatenate([xy_to_d4rl_position(layout, obs[:, :2]), xy_vector_to_d4rl(obs[:, 2:4])], axis=1)


def check_fits_maze(raw: ExternalData, env: Maze2D, xy: np.ndarray, task: str) -> None:
    """Refuse data whose positions lie in walls or outside the maze (data of another maze, or other coordinates)."""
    cells = np.stack(
        [np.floor(env.layout.height / 2 - xy[:, 1]), np.floor(xy[:, 0] + env.layout.width / 2)], axis=1
    ).astype(int)
    free = np.array([env.layout.is_free(int(r), int(c)) for r, c in cells])
    off = 1.0 - float(free.mean())
    if off > MAX_OFF_MAZE:
        raise raw.fail(
            "observations",
            f"places {off:.0%} of its positions in walls or outside maze {env.name} of task {task} "
            f"(at most {MAX_OFF_MAZE:.0%} allowed): data of another maze?",
        )


def maze_trajectories(task: Any, env: Maze2D, raw: ExternalData) -> Trajectories:
    """External Maze2D data as the task's dataset: D4RL's coordinates converted to ours, Minari's PointMaze
    observations (dicts) taken from their ``observation`` entry; episodes as the source ends them (D4RL's stream:
    where the goal changes)."""
    raw.check_dim("observations", raw.observations, env.obs_dim, task.name)
    raw.check_dim("actions", raw.actions, env.act_dim, task.name)
    if raw.format == "d4rl":
        obs = d4rl_observation_to_ours(env.layout, raw.observations)
        actions = d4rl_vector_to_xy(raw.actions)
        coordinates = "converted from D4RL's (x = row, y = column)"
    else:
        obs, actions = raw.observations, raw.actions
        coordinates = "gymnasium-robotics (as stored)"
    check_fits_maze(raw, env, obs[:, :2], task.name)
    return raw.trajectories(task.name, obs, actions, {"coordinates": coordinates})


def maze_export_spec(task: Any, env: Maze2D) -> tuple[Any, Any, Any]:
    """The PointMaze env spec of the task's maze (its wall map, continuing task) and our flat spaces."""
    import gymnasium as gym
    import gymnasium_robotics  # noqa: F401  (registers the PointMaze envs)

    base = gym.spec("PointMaze_UMaze-v3")
    kwargs = {**base.kwargs, "maze_map": env.layout.wall_map(), "continuing_task": True}
    spec = dataclasses.replace(base, kwargs=kwargs, max_episode_steps=env.episode_steps)
    obs_space = gym.spaces.Box(-np.inf, np.inf, (env.obs_dim,), np.float32)
    return spec, obs_space, gym.spaces.Box(-1.0, 1.0, (env.act_dim,), np.float32)
