"""Turning Maze2D plans into actions: Diffuser's plan follower (a PD tracker of the planned states) and the
evaluation controller that plans once (or every ``replan_every`` steps) and follows the plan in between."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from adaptdiffuser.contract import Controller
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.diffusion.guidance import Guidance
from adaptdiffuser.families.maze2d.simulator import PlanningEnv
from adaptdiffuser.planning import Planner


class PlanFollower:
    """Diffuser's Maze2D controller: follow ``plan[t + 1]``; after the plan ends, hold its last position."""

    def __init__(self, env: PlanningEnv, plan_states: np.ndarray) -> None:
        self.env = env
        self.plan_states = plan_states

    def waypoint(self, t: int) -> np.ndarray:
        """The planned state to head for at ``t`` steps after the plan was made."""
        if t + 1 < len(self.plan_states):
            return self.plan_states[t + 1]
        last = self.plan_states[-1].copy()
        last[2:] = 0.0
        return last

    def act(self, obs: np.ndarray, t: int) -> np.ndarray:
        return self.env.tracking_action(obs, self.waypoint(t))


class PlannerController(Controller):
    """Plan at t = 0 (and every ``replan_every`` steps if > 0), follow the plan's states in between;
    ``guidance_for(episodes)`` gives the guidance of a batch of episodes, if any. Each episode's plans are seeded
    by the episode and the step (:meth:`seeds`), so they do not depend on the batch size."""

    def __init__(
        self,
        planner: Planner,
        seed: int,
        replan_every: int = 0,
        guidance_for: Callable[[list[int]], Guidance | None] | None = None,
    ) -> None:
        self.planner = planner
        self.seed = seed
        self.replan_every = replan_every
        self.guidance_for = guidance_for

    def seeds(self, episodes: Sequence[int], t: int) -> list[int]:
        """The seeds of the plans made at step ``t``: episode ``e``'s plan uses ``(seed, e, t)``, whatever its batch."""
        return [derive_seed(self.seed, e, t) for e in episodes]

    def begin(self, envs, obs, episodes):
        self.episodes = episodes
        self.first_plans = None

    def act(self, envs, obs, t):
        if t == 0 or (self.replan_every and t % self.replan_every == 0):
            goals = np.stack([env.goal_state() for env in envs])
            guidance = self.guidance_for(self.episodes) if self.guidance_for else None
            plans = self.planner.plan(obs, goals, self.seeds(self.episodes, t), guidance=guidance)
            obs_part = plans[:, :, self.planner.act_dim :]
            self.followers = [PlanFollower(env, p) for env, p in zip(envs, obs_part, strict=True)]
            self.plan_time = t
            if self.first_plans is None:
                self.first_plans = obs_part
        return np.stack([f.act(o, t - self.plan_time) for f, o in zip(self.followers, obs, strict=True)])
