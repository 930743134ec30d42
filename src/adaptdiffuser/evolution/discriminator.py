"""The rule-based discriminator (paper section 4.2): track each generated state sequence in the real
simulator, reject plans the dynamics cannot follow, score the executed trajectories and select.

What is kept is the *executed* trajectory (real states and actions), never the raw plan.

The family supplies what depends on its tasks: the simulator (with the goal-task methods ``set_goal_state``,
``reward`` and ``tracking_error`` beside :class:`~adaptdiffuser.contract.Simulator`'s), the controller that
follows a plan's states (a :data:`FollowerFactory`) and any :class:`SelectionRule` beyond the generic ``quantile``
and ``top_k`` ones; plans of its own kinds that are not ranked (``ranked`` leaves them out) it judges itself, from
the :class:`~adaptdiffuser.contract.Judgement`'s trajectories and tracking verdicts.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from tqdm import tqdm

from adaptdiffuser.config import DiscriminateParams
from adaptdiffuser.contract import Judgement, TrackedTrajectory


class PlanFollowing(Protocol):
    """A controller following one plan's states: the planned state it heads for ``t`` steps after the plan was
    made, and the action it takes from ``obs`` then."""

    def waypoint(self, t: int) -> np.ndarray: ...

    def act(self, obs: np.ndarray, t: int) -> np.ndarray: ...


#: ``(env, planned_states) -> follower``: the family's plan-following controller (the one its evaluation uses)
FollowerFactory = Callable[[Any, np.ndarray], PlanFollowing]


def track_plan(
    env: Any, planned_states: np.ndarray, follower: FollowerFactory, goal: np.ndarray | None = None
) -> TrackedTrajectory:
    """Start the simulator at ``planned_states[0]`` and follow the plan with ``follower(env, planned_states)``
    (the controller evaluation uses); the error at step t is ``env.tracking_error`` of the executed and planned
    next states. Rewards are measured against ``goal`` when given (the task's goal), else the env's goal."""
    if goal is not None:
        env.set_goal_state(goal)
    controller = follower(env, planned_states)
    obs = env.set_state(planned_states[0])
    observations = [obs]
    actions, errors, rewards = [], [], [env.reward(obs)]
    for t in range(len(planned_states) - 1):
        action = controller.act(obs, t)
        obs = env.step(action).observation
        observations.append(obs)
        actions.append(action)
        errors.append(env.tracking_error(obs, controller.waypoint(t)))
        rewards.append(env.reward(obs))
    actions.append(controller.act(obs, len(planned_states) - 1))  # past the plan's end, as the follower acts there
    rewards_arr = np.asarray(rewards, dtype=np.float64)
    hits = np.flatnonzero(rewards_arr > 0)
    return TrackedTrajectory(
        observations=np.asarray(observations),
        actions=np.asarray(actions).reshape(len(actions), env.act_dim),
        errors=np.asarray(errors, dtype=np.float64),
        rewards=rewards_arr,
        steps_to_goal=int(hits[0]) if len(hits) else -1,
    )


def planned_trajectory(
    env: Any, planned_states: np.ndarray, planned_actions: np.ndarray, goal: np.ndarray | None = None
) -> TrackedTrajectory:
    """A plan taken at its word, without the simulator (the no-discriminator ablation): the planned states and
    actions, zero tracking error, and the protocol reward of each planned state."""
    if goal is not None:
        env.set_goal_state(goal)
    rewards = np.array([env.reward(s) for s in planned_states], dtype=np.float64)
    hits = np.flatnonzero(rewards > 0)
    return TrackedTrajectory(
        observations=np.asarray(planned_states),
        actions=np.asarray(planned_actions).reshape(len(planned_states), env.act_dim),
        errors=np.zeros(len(planned_states) - 1),
        rewards=rewards,
        steps_to_goal=int(hits[0]) if len(hits) else -1,
    )


def passes_tracking(tracked: TrackedTrajectory, threshold: float) -> bool:
    """Dynamics consistency: every executed state stays within ``threshold`` of the planned one."""
    return tracked.max_error <= threshold


def select_by_quantile(scores: np.ndarray, quantile: float) -> np.ndarray:
    """Indices of scores at or above the ``quantile``; never empty for a non-empty input (the best is kept)."""
    if not 0.0 <= quantile <= 1.0:
        raise ValueError(f"quantile must be in [0, 1], got {quantile}")
    scores = np.asarray(scores, dtype=np.float64)
    if scores.size == 0:
        return np.zeros(0, dtype=np.int64)
    keep = np.flatnonzero(scores >= np.quantile(scores, quantile))
    return keep if keep.size else np.array([int(np.argmax(scores))])


def select_top_k(scores: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` best scores (all of them if fewer), best first; at least one when non-empty."""
    if k <= 0:
        raise ValueError(f"k must be positive, got {k}")
    return np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable")[:k]


class SelectionRule(Protocol):
    """Which trajectories to keep, from their real returns ``R`` and lengths ``L`` (numbers of states, that is the
    model's horizon): positions into those arrays, best first where the rule ranks."""

    def select(self, returns: np.ndarray, lengths: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class QuantileRule:
    """Keep the returns at or above the ``quantile`` (never none)."""

    quantile: float

    def select(self, returns: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        return select_by_quantile(returns, self.quantile)


@dataclass(frozen=True)
class TopKRule:
    """Keep the ``k`` best returns."""

    k: int

    def select(self, returns: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        return select_top_k(returns, self.k)


def generic_selection_rule(cfg: DiscriminateParams) -> SelectionRule:
    """The family-independent rule ``cfg.rule`` names (``quantile`` or ``top_k``); families give the others."""
    if cfg.rule == "quantile":
        return QuantileRule(cfg.quantile)
    if cfg.rule == "top_k":
        return TopKRule(cfg.top_k)
    raise ValueError(f"the selection rule {cfg.rule!r} is not a generic one (quantile, top_k); the family gives it")


def select(trajectories: list[TrackedTrajectory], candidates: np.ndarray, rule: SelectionRule) -> np.ndarray:
    """Indices (among ``candidates``) kept by ``rule``, scored by real reward ``R`` and length ``L`` (the number
    of states, that is the model's horizon)."""
    candidates = np.asarray(candidates, dtype=np.int64)
    if candidates.size == 0:
        return candidates
    returns = np.array([trajectories[i].total_reward for i in candidates])
    lengths = np.array([len(trajectories[i].observations) for i in candidates], dtype=np.int64)
    return candidates[rule.select(returns, lengths)]


def discriminate(
    env: Any,
    states: list[np.ndarray],
    actions: list[np.ndarray],
    goals: np.ndarray,
    cfg: DiscriminateParams,
    rule: SelectionRule,
    follower: FollowerFactory,
    ranked: np.ndarray | None = None,
    progress: bool = True,
) -> Judgement:
    """Judge generated plans: track each in the simulator with ``follower`` (or, with ``cfg.tracking`` off, take
    it as planned), reject those whose tracking error exceeds ``cfg.max_error``, and keep what ``rule`` (the one
    ``cfg.rule`` names) selects among the rest of the plans ``ranked`` marks (a boolean mask; default all)."""
    ranked = np.ones(len(states), dtype=bool) if ranked is None else np.asarray(ranked, dtype=bool)
    if ranked.shape != (len(states),):
        raise ValueError(f"ranked marks {ranked.shape[0]} plans, not the {len(states)} generated")
    judged = []
    for plan_states, plan_actions, goal in tqdm(
        list(zip(states, actions, goals, strict=True)), desc="discriminate", disable=not progress, mininterval=2.0
    ):
        if cfg.tracking:
            judged.append(track_plan(env, plan_states, follower, goal))
        else:
            judged.append(planned_trajectory(env, plan_states, plan_actions, goal))
    passed = np.array([passes_tracking(t, cfg.max_error) for t in judged], dtype=bool)
    kept = select(judged, np.flatnonzero(passed & ranked), rule)
    return Judgement(trajectories=judged, passed_tracking=passed, kept=kept)
