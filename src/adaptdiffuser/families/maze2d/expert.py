"""Expert data by D4RL's Maze2D recipe: one continuous waypoint-expert stream with random goals, cut into
episodes where the agent leaves the evaluation goal (Diffuser's ``maze2d_set_terminals``)."""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from adaptdiffuser.contract import Controller
from adaptdiffuser.data.schema import Trajectories
from adaptdiffuser.families.maze2d.simulator import Maze2D


def collect_expert_stream(env: Maze2D, steps: int, seed: int, progress: bool = True) -> Trajectories:
    """Run the expert for ``steps`` steps, switching to a new random goal cell whenever one is reached."""
    rng = np.random.default_rng(seed)
    env.seed_expert(seed)
    eval_goal = env.goal_xy.copy()
    free = env.layout.free_cells
    obs = env.reset(rng)
    env.set_goal(free[rng.integers(len(free))])
    observations = np.empty((steps, env.obs_dim), dtype=np.float32)
    actions = np.empty((steps, env.act_dim), dtype=np.float32)
    for t in tqdm(range(steps), desc="collect", disable=not progress, mininterval=1.0):
        if np.linalg.norm(obs[:2] - env.goal_xy) <= env.goal_radius:
            env.set_goal(free[rng.integers(len(free))])
        action = env.expert_action(obs)
        observations[t] = obs
        actions[t] = action
        obs = env.step(action).observation
    at_goal = np.linalg.norm(observations[:, :2] - eval_goal, axis=1) <= env.goal_radius
    timeout = np.zeros(steps, dtype=bool)
    timeout[:-1] = at_goal[:-1] & ~at_goal[1:]
    timeout[-1] = True
    episode_id = np.concatenate([[0], np.cumsum(timeout[:-1])]).astype(np.int64)
    starts = np.flatnonzero(np.concatenate([[True], episode_id[1:] != episode_id[:-1]]))
    step = np.arange(steps) - np.repeat(starts, np.diff(np.concatenate([starts, [steps]])))
    rewards = at_goal.astype(np.float32)
    return Trajectories(
        episode_id=episode_id,
        step=step,
        observation=observations,
        action=actions,
        reward=rewards,
        terminal=np.zeros(steps, dtype=bool),
        timeout=timeout,
        metadata={},
    )


class ExpertController(Controller):
    """The scripted expert of each environment (the R_max reference)."""

    def __init__(self, seed: int) -> None:
        self.seed = seed

    def begin(self, envs, obs, episodes):
        for env, ep in zip(envs, episodes, strict=True):
            env.seed_expert(int(np.random.default_rng([self.seed, ep, 2]).integers(2**31)))

    def act(self, envs, obs, t):
        return np.stack([env.expert_action(o) for env, o in zip(envs, obs, strict=True)])
