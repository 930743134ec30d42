"""The evaluation protocol: fixed-seed episodes, run in lock-step batches, scored against reference returns."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from tqdm import tqdm

from adaptdiffuser.contract import Controller, EpisodeBatchResult, Simulator
from adaptdiffuser.intervals import win_rate

EnvFactory = Callable[[], Simulator]
ResetFn = Callable[[Simulator, int], np.ndarray]


def episode_rng(seed: int, episode: int) -> np.random.Generator:
    """The random source of one evaluation episode (start state, random actions)."""
    return np.random.default_rng([seed, episode])


def normalized_score(returns: np.ndarray | float, r_min: float, r_max: float) -> np.ndarray | float:
    """D4RL's normalized score: 100 * (R - R_min) / (R_max - R_min)."""
    if r_max <= r_min:
        raise ValueError(f"reference returns must satisfy R_max > R_min, got R_min={r_min}, R_max={r_max}")
    return 100.0 * (np.asarray(returns, dtype=np.float64) - r_min) / (r_max - r_min)


def standard_error(values: np.ndarray | list[float]) -> float:
    """Standard error of the mean (sample standard deviation / sqrt(n)); 0 for fewer than two values."""
    values = np.asarray(values, dtype=np.float64)
    return float(values.std(ddof=1) / np.sqrt(len(values))) if len(values) > 1 else 0.0


def paired_gain(scores: np.ndarray, control_scores: np.ndarray) -> dict[str, float | int]:
    """The gain of a model over its control evaluated on the same episodes (same seeds, same start states):
    mean and standard error of the per-episode differences ``scores - control_scores``, and the win rate (the share
    of episodes the model scores above its control, ties half)."""
    scores, control_scores = np.asarray(scores, dtype=np.float64), np.asarray(control_scores, dtype=np.float64)
    if scores.shape != control_scores.shape or scores.ndim != 1:
        raise ValueError(
            f"paired scores need one value per episode on both sides: {scores.shape} vs {control_scores.shape}"
        )
    diff = scores - control_scores
    return {
        "gain_mean": float(diff.mean()),
        "gain_stderr": standard_error(diff),
        "gain_n_episodes": len(diff),
        "win_rate": win_rate(scores, control_scores),
    }


class RandomController(Controller):
    """Uniform random actions in [-1, 1] (the R_min reference)."""

    def __init__(self, seed: int) -> None:
        self.seed = seed

    def begin(self, envs, obs, episodes):
        self.rngs = [np.random.default_rng([self.seed, ep, 1]) for ep in episodes]

    def act(self, envs, obs, t):
        return np.stack([rng.uniform(-1.0, 1.0, size=env.act_dim) for env, rng in zip(envs, self.rngs, strict=True)])


def run_episodes(
    make_env: EnvFactory,
    controller: Controller,
    n_episodes: int,
    seed: int,
    batch_size: int,
    desc: str = "evaluate",
    progress: bool = True,
    reset: ResetFn | None = None,
) -> EpisodeBatchResult:
    """Run ``n_episodes`` protocol episodes in batches of ``batch_size``; episode ``i`` starts from
    ``reset(env, i)``, by default the protocol's random start drawn from :func:`episode_rng`. An episode ends
    after ``episode_steps`` steps or when its simulator reports termination; a terminated simulator is not
    stepped again (its observation stays at the last state, its reward at zero) while the others go on."""
    if reset is None:

        def reset(env: Simulator, episode: int) -> np.ndarray:
            return env.reset(episode_rng(seed, episode))

    envs = [make_env() for _ in range(min(batch_size, n_episodes))]
    result = EpisodeBatchResult()
    bar = tqdm(total=n_episodes, desc=desc, disable=not progress)
    for first in range(0, n_episodes, batch_size):
        episodes = list(range(first, min(first + batch_size, n_episodes)))
        batch_envs = envs[: len(episodes)]
        obs = np.stack([reset(env, ep) for env, ep in zip(batch_envs, episodes, strict=True)])
        horizon = batch_envs[0].episode_steps
        trace = np.empty((horizon + 1, len(episodes), obs.shape[1]))
        trace[0] = obs
        rewards = np.zeros((horizon, len(episodes)))
        lengths = np.full(len(episodes), horizon)
        done = np.zeros(len(episodes), dtype=bool)
        controller.begin(batch_envs, obs, episodes)
        for t in range(horizon):
            controller.active = ~done
            actions = controller.act(batch_envs, obs, t)
            obs = obs.copy()
            for i in np.flatnonzero(~done):
                step = batch_envs[i].step(actions[i])
                obs[i], rewards[t, i] = step.observation, step.reward
                if step.terminated:
                    done[i], lengths[i] = True, t + 1
            trace[t + 1] = obs
            if done.all():
                trace[t + 2 :] = obs
                break
        controller.active = None
        plans = controller.first_plans
        for i, ep in enumerate(episodes):
            hits = np.flatnonzero(rewards[:, i] > 0)
            result.episodes.append(ep)
            result.returns.append(float(rewards[:, i].sum()))
            result.final_success.append(bool(rewards[lengths[i] - 1, i] > 0))
            result.first_goal_step.append(int(hits[0]) if len(hits) else -1)
            result.starts.append(trace[0, i])
            result.goals.append(batch_envs[i].goal_state())
            result.executed.append(trace[: lengths[i] + 1, i])
            result.plans.append(None if plans is None else plans[i])
            result.lengths.append(int(lengths[i]))
            result.terminated.append(bool(done[i]))
        bar.update(len(episodes))
    bar.close()
    return result


def summarize(result: EpisodeBatchResult, r_min: float, r_max: float) -> dict[str, float | int]:
    """The score metrics of an evaluation: normalized score mean and standard error over episodes, mean return."""
    returns = np.asarray(result.returns)
    scores = normalized_score(returns, r_min, r_max)
    n = len(returns)
    return {
        "score_mean": float(scores.mean()),
        "score_stderr": standard_error(scores),
        "return_mean": float(returns.mean()),
        "n_episodes": int(n),
    }
