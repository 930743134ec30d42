"""95 % intervals of a mean over training seeds that keep their coverage with the three to five seeds we run.

**Over seeds** (two or more): a Student-t interval over the per-seed means, each seed's mean taken over its episodes
(every seed weighs the same, as in the summaries' ``score_mean``): ``mean ± t(n-1) x sd(seed means) / sqrt(n)``.
A seed mean holds both the seed's own effect and its episode noise, so their spread holds both, however far the seeds
disagree; with seed means of hundreds of episodes (close to normal) the interval is exact. Simulated with 3 and 5
seeds whose means spread with SD 3 and 6 under an episode SD of 40 (500 episodes), it covers the true mean 95
times in 100 (94.8-95.6; ``tests/test_intervals.py``), where the two-level bootstrap used before (seeds, then
episodes) covered 79-89: resampling three seeds cannot show how far seed means spread (Agarwal et al. 2021 resample
runs over many tasks).

**Over episodes** (:func:`episode_interval`): the seeds (the trained models) held fixed and each seed's episodes
resampled, a stratified percentile bootstrap. It is the uncertainty of these models' mean over the start-state
distribution, not of what another training seed would give; with one seed it is the only interval there is, and it
is labelled "one seed: over episodes", never as an interval over seeds.

For a gain, the episodes are the per-episode differences between a model and its control played on the same start
states (paired), and the win rate is the share of episodes a model scores above its control (ties half).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: resamples of the episode bootstrap: the Monte-Carlo error of a 95 % percentile bound is then well below 0.1 point
REPS = 20_000
CONFIDENCE = 0.95
#: what a one-seed interval is called wherever it is printed: it is over episodes, never over seeds
ONE_SEED = "one seed: over episodes"
_CHUNK = 4_000_000


def _as_groups(per_seed: Sequence[Sequence[float] | np.ndarray]) -> list[np.ndarray]:
    groups = [np.asarray(values, dtype=np.float64).ravel() for values in per_seed]
    if not groups or any(g.size == 0 for g in groups):
        raise ValueError("an interval needs at least one seed and at least one episode per seed")
    if any(not np.all(np.isfinite(g)) for g in groups):
        raise ValueError("an interval needs finite scores (a NaN or inf among the episodes)")
    return groups


def _check_confidence(confidence: float) -> None:
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")


def seed_interval(seed_means: np.ndarray, confidence: float = CONFIDENCE) -> tuple[np.ndarray, np.ndarray]:
    """The Student-t interval of the mean over seeds from the per-seed means on the last axis (two or more; leading
    axes are independent cases): ``(low, high)``, each of the leading axes' shape."""
    from scipy import stats  # here: the import costs a third of a second, and only intervals over seeds need it

    _check_confidence(confidence)
    means = np.asarray(seed_means, dtype=np.float64)
    n = means.shape[-1] if means.ndim else 0
    if n < 2:
        raise ValueError(f"an interval over seeds needs two or more seeds, got {n}: use episode_interval")
    if not np.all(np.isfinite(means)):
        raise ValueError("an interval over seeds needs finite seed means")
    centre = means.mean(axis=-1)
    half = stats.t.ppf(0.5 + confidence / 2.0, n - 1) * means.std(axis=-1, ddof=1) / np.sqrt(n)
    return centre - half, centre + half


def bootstrap_episode_means(
    per_seed: Sequence[Sequence[float] | np.ndarray], reps: int, rng: np.random.Generator
) -> np.ndarray:
    """``reps`` bootstrap replicates of the mean over seeds of the seeds' episode means, each seed's episodes drawn
    with replacement and the seeds kept as they are."""
    groups = _as_groups(per_seed)
    total = np.zeros(reps)
    for group in groups:
        chunk = max(1, _CHUNK // group.size)  # bounded memory: at most _CHUNK draws at a time
        for start in range(0, reps, chunk):
            stop = min(start + chunk, reps)
            total[start:stop] += group[rng.integers(0, group.size, size=(stop - start, group.size))].mean(axis=1)
    return total / len(groups)


def episode_interval(
    per_seed: Sequence[Sequence[float] | np.ndarray],
    seed: int = 0,
    reps: int = REPS,
    confidence: float = CONFIDENCE,
) -> tuple[float, float]:
    """The percentile bootstrap interval over episodes (seeds held fixed) of the mean over seeds: ``(low, high)``.
    Deterministic for a given ``seed``."""
    _check_confidence(confidence)
    replicates = bootstrap_episode_means(per_seed, reps, np.random.default_rng(seed))
    tail = (1.0 - confidence) / 2.0
    low, high = np.quantile(replicates, [tail, 1.0 - tail])
    return float(low), float(high)


def interval(
    per_seed: Sequence[Sequence[float] | np.ndarray],
    seed: int = 0,
    reps: int = REPS,
    confidence: float = CONFIDENCE,
) -> dict[str, float | int | str]:
    """The mean over seeds of each seed's episode mean and its 95 % intervals: ``{"mean", "ci_low", "ci_high",
    "over", "episode_ci_low", "episode_ci_high", "n_seeds", "n_episodes"}``. ``ci_*`` is the t-interval over seeds
    (``over: "seeds"``) with two or more seeds, and the interval over episodes with one (``over: "episodes"``);
    ``episode_ci_*`` is always over episodes (:func:`episode_interval`, deterministic for a given ``seed``);
    ``n_episodes``: the fewest a seed has."""
    groups = _as_groups(per_seed)
    episode_low, episode_high = episode_interval(groups, seed, reps, confidence)
    means = np.array([g.mean() for g in groups])
    if len(groups) > 1:
        low, high = seed_interval(means, confidence)
        bounds, over = (float(low), float(high)), "seeds"
    else:
        bounds, over = (episode_low, episode_high), "episodes"
    return {
        "mean": float(means.mean()),
        "ci_low": bounds[0],
        "ci_high": bounds[1],
        "over": over,
        "episode_ci_low": episode_low,
        "episode_ci_high": episode_high,
        "n_seeds": len(groups),
        "n_episodes": int(min(g.size for g in groups)),
    }


def win_rate(scores: np.ndarray, control_scores: np.ndarray) -> float:
    """The share of episodes in which a model scores above its control on the same start state, ties counting
    half (not rliable's probability of improvement, which compares runs)."""
    a, b = np.asarray(scores, dtype=np.float64), np.asarray(control_scores, dtype=np.float64)
    if a.shape != b.shape or a.size == 0:
        raise ValueError(f"a win rate needs the same episodes on both sides: {a.size} against {b.size}")
    return float(np.mean((a > b) + 0.5 * (a == b)))


def paired_interval(
    scores: Sequence[Sequence[float] | np.ndarray],
    control_scores: Sequence[Sequence[float] | np.ndarray],
    seed: int = 0,
    reps: int = REPS,
    confidence: float = CONFIDENCE,
) -> dict[str, float | int | str]:
    """The gain of models over their controls, each seed's pair played on the same episodes: :func:`interval` of
    the per-episode differences, plus the ``win_rate`` (:func:`win_rate`, mean over seeds)."""
    if len(scores) != len(control_scores):
        raise ValueError(f"{len(scores)} seeds of scores against {len(control_scores)} of control scores")
    models, controls = _as_groups(scores), _as_groups(control_scores)
    for s, (a, b) in enumerate(zip(models, controls, strict=True)):
        if a.shape != b.shape:
            raise ValueError(f"seed {s}: {a.size} episodes against {b.size} of its control; pairs need the same")
    out = interval([a - b for a, b in zip(models, controls, strict=True)], seed, reps, confidence)
    wins = [win_rate(a, b) for a, b in zip(models, controls, strict=True)]
    return out | {"win_rate": float(np.mean(wins))}


def describe(m: dict, digits: int = 1) -> str:
    """``mean [low, high]`` of an :func:`interval` result, labelled ``(one seed: over episodes)`` when it has one
    seed."""
    text = f"{m['mean']:.{digits}f} [{m['ci_low']:.{digits}f}, {m['ci_high']:.{digits}f}]"
    return text if m.get("over", "seeds") == "seeds" else f"{text} ({ONE_SEED})"
