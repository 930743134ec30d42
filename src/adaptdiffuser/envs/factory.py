"""Build the environment named in params."""

from __future__ import annotations

from adaptdiffuser.config import Params
from adaptdiffuser.envs.maze2d import Maze2D, resolve_layout


def make_env(params: Params) -> Maze2D:
    """A fresh simulator for the task in ``params``: protocol from ``env``, expert gains from ``expert``,
    plan-follower gains from ``planner``."""
    e, x, pl = params.env, params.expert, params.planner
    return Maze2D(
        resolve_layout(e.maze, e.layout),
        name=e.maze if e.layout is None else "custom",
        episode_steps=e.episode_steps,
        goal_radius=e.goal_radius,
        reset_pos_noise=e.reset_pos_noise,
        reset_vel_noise=e.reset_vel_noise,
        random_goal=e.random_goal,
        expert_p_gain=x.p_gain,
        expert_d_gain=x.d_gain,
        expert_jitter=x.jitter,
        expert_waypoint_radius=x.waypoint_radius,
        tracking_p_gain=pl.tracking_p_gain,
        tracking_d_gain=pl.tracking_d_gain,
    )
