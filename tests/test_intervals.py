"""The two-level bootstrap (training seeds, then episodes within each) behind every reported interval."""

from __future__ import annotations

import numpy as np
import pytest

from adaptdiffuser.evaluation import standard_error
from adaptdiffuser.intervals import interval, paired_interval


def test_one_seed_gives_the_normal_interval_of_its_episodes() -> None:
    scores = np.random.default_rng(0).normal(40.0, 30.0, size=400)
    out = interval([scores])
    half = 1.96 * standard_error(scores)
    assert out["mean"] == pytest.approx(scores.mean())
    assert out["ci_low"] == pytest.approx(scores.mean() - half, abs=0.1 * half)
    assert out["ci_high"] == pytest.approx(scores.mean() + half, abs=0.1 * half)
    assert (out["n_seeds"], out["n_episodes"]) == (1, 400)


def test_an_interval_holds_the_true_mean_at_least_95_times_in_100_erring_wide() -> None:
    rng = np.random.default_rng(1)
    hits = 0
    for trial in range(300):
        seeds = [rng.normal(10.0, 5.0, size=60) for _ in range(4)]
        out = interval(seeds, seed=trial, reps=2000)
        hits += out["ci_low"] <= 10.0 <= out["ci_high"]
    assert 0.94 <= hits / 300 <= 0.995, hits  # about 0.975: both levels resampled (intervals.py)


def test_seeds_that_disagree_widen_the_interval_beyond_their_episode_noise() -> None:
    rng = np.random.default_rng(2)
    noise = [rng.normal(0.0, 10.0, size=100) for _ in range(3)]
    agree = interval([n + 50.0 for n in noise])
    disagree = interval([n + shift for n, shift in zip(noise, (35.0, 50.0, 65.0), strict=True)])
    assert disagree["ci_high"] - disagree["ci_low"] > 3 * (agree["ci_high"] - agree["ci_low"])


def test_the_same_seed_gives_the_same_interval_and_another_seed_another() -> None:
    scores = [np.random.default_rng(6).normal(0.0, 1.0, size=30) + shift for shift in (0.0, 1.0)]
    assert interval(scores, seed=3) == interval(scores, seed=3)
    assert interval(scores, seed=3)["ci_low"] != interval(scores, seed=4)["ci_low"]


def test_a_paired_gain_is_the_interval_of_episode_differences_with_its_probability_of_improvement() -> None:
    rng = np.random.default_rng(5)
    control = [rng.normal(40.0, 20.0, size=200) for _ in range(3)]
    model = [c + 2.0 for c in control]  # better on every start state by 2 points
    out = paired_interval(model, control)
    assert out["mean"] == pytest.approx(2.0) and out["ci_low"] == pytest.approx(2.0)
    assert out["probability_of_improvement"] == 1.0
    assert paired_interval(control, control)["probability_of_improvement"] == 0.5


def test_bad_input_is_refused_with_a_clear_error() -> None:
    with pytest.raises(ValueError, match="same"):
        paired_interval([np.ones(5)], [np.ones(6)])
    with pytest.raises(ValueError, match="at least one episode"):
        interval([np.ones(3), np.array([])])
    with pytest.raises(ValueError, match="finite"):
        interval([np.array([1.0, np.nan])])
    with pytest.raises(ValueError, match="confidence"):
        interval([np.ones(3)], confidence=1.5)
