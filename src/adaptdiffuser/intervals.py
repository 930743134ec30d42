"""Confidence intervals the way the field reports them (Agarwal et al., NeurIPS 2021): a two-level bootstrap
that resamples training seeds and, within each resampled seed, its evaluation episodes, so that an interval over
three seeds carries both the spread between seeds and each seed's episode noise.

rliable's stratified bootstrap resamples runs (seeds) alone; here each seed is a sample of episodes as well, which
is what makes a 50-episode evaluation's noise show in the interval. The statistic is the mean over seeds of each
seed's mean (every seed weighs the same, as in the summaries' ``score_mean``); for a gain, the episodes are the
per-episode differences between a model and its control played on the same start states (paired).

Resampling both levels counts a seed's episode noise twice over (once in the spread of the drawn seed means, once in
the redrawn episodes), so the interval errs wide: with four seeds of 60 episodes that agree, it holds the true mean
about 97 times in 100 rather than 95 (``tests/test_intervals.py``). With the three to five seeds we run, that is the
side to err on: a seeds-only bootstrap cannot reach beyond the seeds' own range.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: resamples of a bootstrap: the Monte-Carlo error of a 95 % percentile bound is then well below 0.1 point
REPS = 20_000
CONFIDENCE = 0.95
_CHUNK = 4_000_000


def _as_groups(per_seed: Sequence[Sequence[float] | np.ndarray]) -> list[np.ndarray]:
    groups = [np.asarray(values, dtype=np.float64).ravel() for values in per_seed]
    if not groups or any(g.size == 0 for g in groups):
        raise ValueError("a bootstrap needs at least one seed and at least one episode per seed")
    if any(not np.all(np.isfinite(g)) for g in groups):
        raise ValueError("a bootstrap needs finite scores (a NaN or inf among the episodes)")
    return groups


def bootstrap_means(
    per_seed: Sequence[Sequence[float] | np.ndarray], reps: int, rng: np.random.Generator
) -> np.ndarray:
    """``reps`` bootstrap replicates of the mean over seeds of the seeds' episode means: each replicate draws the
    seeds with replacement, then each drawn seed's episodes with replacement."""
    groups = _as_groups(per_seed)
    n_seeds = len(groups)
    drawn = rng.integers(0, n_seeds, size=(reps, n_seeds))
    replicate_means = np.empty((reps, n_seeds))
    for s, group in enumerate(groups):
        rows, cols = np.nonzero(drawn == s)
        chunk = max(1, _CHUNK // group.size)  # bounded memory: at most _CHUNK draws at a time
        for start in range(0, rows.size, chunk):
            stop = min(start + chunk, rows.size)
            picks = rng.integers(0, group.size, size=(stop - start, group.size))
            replicate_means[rows[start:stop], cols[start:stop]] = group[picks].mean(axis=1)
    return replicate_means.mean(axis=1)


def interval(
    per_seed: Sequence[Sequence[float] | np.ndarray],
    seed: int = 0,
    reps: int = REPS,
    confidence: float = CONFIDENCE,
) -> dict[str, float | int]:
    """The mean over seeds and its two-level percentile bootstrap interval: ``{"mean", "ci_low", "ci_high",
    "n_seeds", "n_episodes"}`` (``n_episodes``: the fewest a seed has). Deterministic for a given ``seed``."""
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    groups = _as_groups(per_seed)
    replicates = bootstrap_means(groups, reps, np.random.default_rng(seed))
    tail = (1.0 - confidence) / 2.0
    low, high = np.quantile(replicates, [tail, 1.0 - tail])
    return {
        "mean": float(np.mean([g.mean() for g in groups])),
        "ci_low": float(low),
        "ci_high": float(high),
        "n_seeds": len(groups),
        "n_episodes": int(min(g.size for g in groups)),
    }


def paired_interval(
    scores: Sequence[Sequence[float] | np.ndarray],
    control_scores: Sequence[Sequence[float] | np.ndarray],
    seed: int = 0,
    reps: int = REPS,
    confidence: float = CONFIDENCE,
) -> dict[str, float | int]:
    """The gain of models over their controls, each seed's pair played on the same episodes: :func:`interval` of
    the per-episode differences, plus the probability of improvement (the chance that a model's episode scores
    above its control's on the same start state, ties counting half; mean over seeds)."""
    if len(scores) != len(control_scores):
        raise ValueError(f"{len(scores)} seeds of scores against {len(control_scores)} of control scores")
    models, controls = _as_groups(scores), _as_groups(control_scores)
    for s, (a, b) in enumerate(zip(models, controls, strict=True)):
        if a.shape != b.shape:
            raise ValueError(f"seed {s}: {a.size} episodes against {b.size} of its control; pairs need the same")
    out = interval([a - b for a, b in zip(models, controls, strict=True)], seed, reps, confidence)
    wins = [np.mean((a > b) + 0.5 * (a == b)) for a, b in zip(models, controls, strict=True)]
    return out | {"probability_of_improvement": float(np.mean(wins))}
