"""The intervals behind every reported figure: a Student-t interval over training seeds' means, and the interval
over episodes (seeds held fixed), the only one a single seed has."""

from __future__ import annotations

import numpy as np
import pytest

from adaptdiffuser.evaluation import standard_error
from adaptdiffuser.intervals import (
    ONE_SEED,
    describe,
    episode_interval,
    interval,
    paired_interval,
    seed_interval,
    win_rate,
)


@pytest.mark.parametrize("n_seeds", [3, 5])
@pytest.mark.parametrize("seed_sd", [0.0, 3.0, 6.0])
def test_the_interval_over_seeds_holds_the_true_mean_when_seed_means_disagree(n_seeds: int, seed_sd: float) -> None:
    """Seeds whose true means spread with ``seed_sd`` around 50, each 500 episodes of SD 40: the 95 % interval over
    seeds holds 50 at least 93 times in 100 (the two-level bootstrap it replaced held it 79-89 times with SD 3-6),
    and is not needlessly wide (at most 97)."""
    rng = np.random.default_rng(89 + n_seeds)
    trials, episodes = 4000, 500
    true_means = 50.0 + rng.normal(0.0, seed_sd, size=(trials, n_seeds, 1))
    scores = true_means + rng.normal(0.0, 40.0, size=(trials, n_seeds, episodes))
    low, high = seed_interval(scores.mean(axis=-1))
    coverage = float(np.mean((low <= 50.0) & (high >= 50.0)))
    assert 0.93 <= coverage <= 0.97, coverage


def test_interval_over_several_seeds_is_the_t_interval_of_their_means_beside_the_one_over_episodes() -> None:
    rng = np.random.default_rng(3)
    seeds = [rng.normal(shift, 40.0, size=500) for shift in (44.0, 50.0, 56.0)]
    out = interval(seeds)
    means = np.array([s.mean() for s in seeds])
    half = 4.302652729911275 * means.std(ddof=1) / np.sqrt(3)  # t(2) at 0.975
    assert out["over"] == "seeds" and (out["n_seeds"], out["n_episodes"]) == (3, 500)
    assert (out["ci_low"], out["ci_high"]) == pytest.approx((means.mean() - half, means.mean() + half))
    # the seeds disagree far beyond their episode noise: the interval over episodes alone is much narrower
    assert out["episode_ci_high"] - out["episode_ci_low"] < 0.3 * (out["ci_high"] - out["ci_low"])
    assert (out["episode_ci_low"], out["episode_ci_high"]) == episode_interval(seeds)


def test_one_seed_gives_the_normal_interval_of_its_episodes_labelled_as_such() -> None:
    scores = np.random.default_rng(0).normal(40.0, 30.0, size=400)
    out = interval([scores])
    half = 1.96 * standard_error(scores)
    assert out["mean"] == pytest.approx(scores.mean()) and out["over"] == "episodes"
    assert out["ci_low"] == pytest.approx(scores.mean() - half, abs=0.1 * half)
    assert out["ci_high"] == pytest.approx(scores.mean() + half, abs=0.1 * half)
    assert (out["ci_low"], out["ci_high"]) == (out["episode_ci_low"], out["episode_ci_high"])
    assert (out["n_seeds"], out["n_episodes"]) == (1, 400)
    assert describe(out).endswith(f"({ONE_SEED})") and ONE_SEED == "one seed: over episodes"
    assert "over episodes" not in describe(interval([scores, scores + 1.0]))


def test_the_interval_over_episodes_holds_the_fixed_seeds_mean() -> None:
    """Seeds held fixed (their true means known), only their episodes redrawn: the episode interval holds the mean
    of the seeds' true means about 95 times in 100."""
    rng = np.random.default_rng(1)
    hits = 0
    for trial in range(300):
        seeds = [rng.normal(mean, 5.0, size=60) for mean in (8.0, 10.0, 12.0, 10.0)]
        low, high = episode_interval(seeds, seed=trial, reps=2000)
        hits += low <= 10.0 <= high
    assert 0.92 <= hits / 300 <= 0.98, hits


def test_the_same_seed_gives_the_same_interval_and_another_seed_another() -> None:
    scores = [np.random.default_rng(6).normal(0.0, 1.0, size=30) + shift for shift in (0.0, 1.0)]
    assert interval(scores, seed=3) == interval(scores, seed=3)
    assert interval(scores, seed=3)["episode_ci_low"] != interval(scores, seed=4)["episode_ci_low"]
    assert interval(scores, seed=3)["ci_low"] == interval(scores, seed=4)["ci_low"]  # the t-interval draws nothing


def test_a_paired_gain_is_the_interval_of_episode_differences_with_its_win_rate() -> None:
    rng = np.random.default_rng(5)
    control = [rng.normal(40.0, 20.0, size=200) for _ in range(3)]
    model = [c + 2.0 for c in control]  # better on every start state by 2 points
    out = paired_interval(model, control)
    assert out["mean"] == pytest.approx(2.0) and out["ci_low"] == pytest.approx(2.0)
    assert out["win_rate"] == 1.0 and "probability_of_improvement" not in out
    assert paired_interval(control, control)["win_rate"] == 0.5
    assert win_rate(np.array([1.0, 2.0, 3.0, 4.0]), np.array([0.0, 2.0, 5.0, 5.0])) == pytest.approx(0.375)


def test_bad_input_is_refused_with_a_clear_error() -> None:
    with pytest.raises(ValueError, match="same"):
        paired_interval([np.ones(5)], [np.ones(6)])
    with pytest.raises(ValueError, match="at least one episode"):
        interval([np.ones(3), np.array([])])
    with pytest.raises(ValueError, match="finite"):
        interval([np.array([1.0, np.nan])])
    with pytest.raises(ValueError, match="confidence"):
        interval([np.ones(3)], confidence=1.5)
    with pytest.raises(ValueError, match="two or more seeds"):
        seed_interval(np.array([1.0]))
    with pytest.raises(ValueError, match="same episodes"):
        win_rate(np.ones(2), np.ones(3))
