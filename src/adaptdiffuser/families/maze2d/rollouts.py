"""The author's Maze2D synthetic data: closed-loop rollouts of the planner in the real simulator.

Each generation task (start, goal and maybe a coin) is run from its start with the evaluation's plan follower: the
planner plans at t = 0 and every ``replan_every`` steps (0: once) from the current state to the goal, the follower
tracks the latest plan, and the rollout ends as soon as the goal is reached (after the coin is picked, for a coin
task) or after ``max_steps`` steps. So rollouts differ in length, and a kept rollout's length is the real number of
steps it took. Tasks run in lock-step batches, but only the rollouts still going are planned for, and the plan task
``i`` makes at step ``t`` uses the seed ``(seed, i, t)``: a rollout does not depend on the batch size.

Training data made from a rollout that ends at the goal is padded by staying there (:func:`settle_at_goal`), so
windows that reach the goal go on at it, at rest: the model learns plans that reach the goal and stay.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from adaptdiffuser.contract import TrackedTrajectory
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.families.maze2d.execution import PlanFollower
from adaptdiffuser.families.maze2d.generation import NavigationTasks
from adaptdiffuser.families.maze2d.gold_coin import CoinObjective
from adaptdiffuser.families.maze2d.simulator import Maze2D
from adaptdiffuser.planning import Planner

#: column of a generated rollouts file: the tracking error of the step into each row's state (0 for the first row)
ERROR_COLUMN = "tracking_error"


@dataclass
class _Trace:
    """One rollout as it runs: the states reached, the actions taken, the follower's errors and the rewards."""

    observations: list[np.ndarray]
    rewards: list[float]
    actions: list[np.ndarray] = field(default_factory=list)
    errors: list[float] = field(default_factory=list)

    def finish(self, last_action: np.ndarray) -> TrackedTrajectory:
        rewards = np.asarray(self.rewards, dtype=np.float64)
        hits = np.flatnonzero(rewards > 0)
        return TrackedTrajectory(
            observations=np.asarray(self.observations),
            actions=np.asarray([*self.actions, last_action]),
            errors=np.asarray(self.errors, dtype=np.float64),
            rewards=rewards,
            steps_to_goal=int(hits[0]) if len(hits) else -1,
        )


def real_length(trajectory: TrackedTrajectory) -> int:
    """L of the paper's rule for a rollout: the steps taken until the goal is first reached, or all the steps taken
    when it never is."""
    return trajectory.steps_to_goal if trajectory.steps_to_goal >= 0 else len(trajectory.observations) - 1


def reached_goal(trajectory: TrackedTrajectory) -> bool:
    """Whether the trajectory ends at its goal (the protocol's reward for its last state is positive)."""
    return bool(trajectory.rewards[-1] > 0)


class RolloutBatch:
    """Lock-step rollouts of some tasks, one simulator each (see the module docstring)."""

    def __init__(
        self,
        envs: list[Maze2D],
        planner: Planner,
        tasks: NavigationTasks,
        rows: np.ndarray,
        seed: int,
        replan_every: int,
        alpha: float = 0.0,
        coin_radius: float = 0.5,
    ) -> None:
        self.envs, self.planner, self.rows, self.seed = envs, planner, np.asarray(rows), seed
        self.replan_every, self.alpha, self.coin_radius = replan_every, alpha, coin_radius
        self.goals = tasks.goals[self.rows]
        self.coins = None if tasks.coins is None else tasks.coins[self.rows]
        self.has_coin = tasks.has_coin()[self.rows]
        self.obs = np.stack(
            [self._reset(env, tasks.starts[i], goal) for env, i, goal in zip(envs, self.rows, self.goals, strict=True)]
        )
        self.picked = ~self.has_coin
        self._check_coins(np.arange(len(self.rows)))
        self.traces = [_Trace([o.copy()], [env.reward(o)]) for env, o in zip(envs, self.obs, strict=True)]
        self.active = ~self._done(np.arange(len(self.rows)))
        self.followers: list[PlanFollower | None] = [None] * len(self.rows)
        self.plan_time = 0

    @staticmethod
    def _reset(env: Maze2D, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
        env.set_goal_state(goal)
        return env.set_state(start)

    def _check_coins(self, idx: np.ndarray) -> None:
        """Mark the coins picked by the current states of rollouts ``idx``."""
        if self.coins is None:
            return
        for i in idx:
            if not self.picked[i] and np.linalg.norm(self.obs[i, :2] - self.coins[i]) <= self.coin_radius:
                self.picked[i] = True

    def _done(self, idx: np.ndarray) -> np.ndarray:
        """Whether rollouts ``idx`` are at their goal with their coin (if any) picked."""
        return np.array([self.traces[i].rewards[-1] > 0 and self.picked[i] for i in idx], dtype=bool)

    def _plan(self, t: int) -> None:
        """New plans for the active rollouts from their current states: coin rollouts that have not picked their
        coin yet are guided toward it, the others plan to the goal unguided."""
        act_dim = self.planner.act_dim
        active = np.flatnonzero(self.active)
        guided = self.has_coin & ~self.picked
        for idx, guide in ((active[~guided[active]], False), (active[guided[active]], True)):
            if not len(idx):
                continue
            guidance = None
            if guide:
                coins = torch.as_tensor(self.coins[idx], dtype=torch.float32, device=self.planner.device)
                guidance = self.planner.guidance(CoinObjective(coins), self.alpha)
            seeds = [derive_seed(self.seed, int(self.rows[i]), t) for i in idx]
            plans = self.planner.plan(self.obs[idx], self.goals[idx], seeds, guidance=guidance)
            for i, plan in zip(idx, plans, strict=True):
                self.followers[i] = PlanFollower(self.envs[i], plan[:, act_dim:])
        self.plan_time = t

    def step(self, t: int) -> None:
        """Step ``t``: replan if due, then one follower action in every active rollout."""
        if t == 0 or (self.replan_every and t % self.replan_every == 0):
            self._plan(t)
        idx = np.flatnonzero(self.active)
        for i in idx:
            follower, env, trace = self.followers[i], self.envs[i], self.traces[i]
            action = follower.act(self.obs[i], t - self.plan_time)
            self.obs[i] = env.step(action).observation
            trace.observations.append(self.obs[i].copy())
            trace.actions.append(action)
            trace.errors.append(env.tracking_error(self.obs[i], follower.waypoint(t - self.plan_time)))
            trace.rewards.append(env.reward(self.obs[i]))
        self._check_coins(idx)
        self.active[idx] = ~self._done(idx)

    def run(self, max_steps: int) -> list[TrackedTrajectory]:
        """Step until every rollout is done or ``max_steps`` steps; the last action of a rollout at its goal is
        zero (it stays), of one that ran out of time the follower's next action."""
        for t in range(max_steps):
            if not self.active.any():
                break
            self.step(t)
        out = []
        for i, trace in enumerate(self.traces):
            last = np.zeros(self.planner.act_dim)
            if self.active[i]:  # out of time: what the follower would do next
                last = self.followers[i].act(self.obs[i], max_steps - self.plan_time)
            out.append(trace.finish(last))
        return out


def run_rollouts(
    make_env: Callable[[], Maze2D],
    planner: Planner,
    tasks: NavigationTasks,
    seed: int,
    replan_every: int,
    max_steps: int,
    batch_size: int,
    alpha: float = 0.0,
    coin_radius: float = 0.5,
    progress: bool = False,
) -> list[TrackedTrajectory]:
    """One closed-loop rollout per task (see the module docstring), run ``batch_size`` tasks at a time; rollout
    ``i`` depends on its task, ``seed`` and the settings only. Coin tasks are guided toward their coin with scale
    ``alpha`` until they pass within ``coin_radius`` of it."""
    if batch_size <= 0 or max_steps <= 0:
        raise ValueError(f"batch_size and max_steps must be positive, got {batch_size} and {max_steps}")
    if replan_every < 0:
        raise ValueError(f"replan_every must be >= 0 (0: plan once), got {replan_every}")
    envs = [make_env() for _ in range(min(batch_size, len(tasks)))]
    out: list[TrackedTrajectory] = []
    starts = range(0, len(tasks), batch_size)
    for first in tqdm(starts, desc="rollouts", disable=not progress):
        rows = np.arange(first, min(first + batch_size, len(tasks)))
        batch = RolloutBatch(envs[: len(rows)], planner, tasks, rows, seed, replan_every, alpha, coin_radius)
        out.extend(batch.run(max_steps))
    return out


def settle_at_goal(trajectory: TrackedTrajectory, stop: int, length: int) -> TrackedTrajectory:
    """``trajectory`` up to its state ``stop`` (where it reached the goal), then at rest there: the same position
    with zero velocity and zero actions until it has ``length`` states (at least ``stop + 1``). The action taken at
    ``stop`` becomes zero too; the rest keep the reward of the state at ``stop``."""
    n = len(trajectory.observations)
    if not 0 <= stop < n:
        raise ValueError(f"stop must index a state of the trajectory (0..{n - 1}), got {stop}")
    pad = max(0, length - (stop + 1))
    rest = trajectory.observations[stop].copy()
    rest[2:] = 0.0
    actions = trajectory.actions[: stop + 1].copy()
    actions[stop] = 0.0
    return TrackedTrajectory(
        observations=np.concatenate([trajectory.observations[: stop + 1], np.repeat(rest[None], pad, axis=0)]),
        actions=np.concatenate([actions, np.zeros((pad, actions.shape[1]))]),
        errors=np.concatenate([trajectory.errors[:stop], np.zeros(pad)]),
        rewards=np.concatenate([trajectory.rewards[: stop + 1], np.full(pad, trajectory.rewards[stop])]),
        steps_to_goal=trajectory.steps_to_goal,
    )
