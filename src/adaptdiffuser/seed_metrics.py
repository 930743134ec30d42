"""Metrics over training seeds: a stage that runs once per seed writes one metrics file holding each seed's
metrics and their aggregate, so every reader (summary, report, sweep) sees one number per phase.

Episodes are averaged within a seed first; the aggregate of every number is its mean over seeds, and every
``<name>_stderr`` beside a ``<name>_mean`` (or a ``<name>``) becomes the standard error of that mean over seeds
when there are two or more. A number a seed could not measure (None: a mean over no episode) is left out of its
mean; None where no seed measured it. With one seed the aggregate is that seed's metrics unchanged (the standard
errors are then over episodes: ``stderr_over`` says which).

A seed's ``<name>_per_episode`` (the list of its episodes' values: scores, or paired gains over a control) stays in
that seed's entry only; the aggregate holds in its place the 95 % intervals of ``<name>_mean``
(:mod:`adaptdiffuser.intervals`): over training seeds as ``<name>_ci_low`` and ``<name>_ci_high`` (a Student-t
interval over the seeds' means; two or more seeds only), and over episodes with the seeds held fixed as
``<name>_episode_ci_low`` and ``<name>_episode_ci_high`` (always; with one seed the only interval, which readers
label "one seed: over episodes")."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from adaptdiffuser.evaluation import standard_error
from adaptdiffuser.intervals import interval

PER_EPISODE = "_per_episode"


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _numbers_of(values: list[Any]) -> list[Any] | None:
    """The numbers among ``values`` when every value is a number or None (not measured) and one is a number."""
    if all(_is_number(v) or v is None for v in values) and any(v is not None for v in values):
        return [v for v in values if v is not None]
    return None


def _mean_of(values: list[Any]) -> Any:
    """Numbers: their mean (ints stay ints when all seeds agree), leaving out the seeds that measured none (None);
    mappings: key by key; anything else: the common value, or None when seeds differ."""
    numbers = _numbers_of(values)
    if numbers is not None:
        values = numbers
    first = values[0]
    if all(_is_number(v) for v in values):
        if all(isinstance(v, int) for v in values) and len(set(values)) == 1:
            return first
        return float(np.mean(values))
    if all(isinstance(v, Mapping) for v in values):
        keys = [k for k in first if all(k in v for v in values)]
        return {k: _mean_of([v[k] for v in values]) for k in keys}
    return first if all(v == first for v in values) else None


def _spread_over_seeds(merged: dict[str, Any], values: list[Mapping[str, Any]]) -> None:
    """Replace, in place and at every depth, each ``<name>_stderr`` by the standard error over seeds of its
    ``<name>_mean`` (or ``<name>``)."""
    for key in list(merged):
        if isinstance(merged[key], dict):
            _spread_over_seeds(merged[key], [v[key] for v in values])
        elif key.endswith("_stderr"):
            name = key.removesuffix("_stderr")
            mean = next((m for m in (f"{name}_mean", name) if m in merged and _is_number(merged[m])), None)
            if mean is not None:
                measured = [float(v[mean]) for v in values if v[mean] is not None]
                merged[key] = standard_error(measured) if len(measured) > 1 else None


def _intervals_in_place(merged: dict[str, Any], values: list[Mapping[str, Any]]) -> None:
    """Replace, in place and at every depth, each ``<name>_per_episode`` that every seed holds by the intervals of
    its mean: over seeds (``<name>_ci_low``, ``<name>_ci_high``; two or more seeds) and over episodes
    (``<name>_episode_ci_low``, ``<name>_episode_ci_high``)."""
    for key in list(merged):
        if isinstance(merged[key], dict):
            _intervals_in_place(merged[key], [v[key] for v in values])
    for key in [k for k in values[0] if k.endswith(PER_EPISODE)]:
        merged.pop(key, None)
        if all(isinstance(v.get(key), list) and v[key] for v in values):
            name = key.removesuffix(PER_EPISODE)
            bounds = interval([v[key] for v in values])
            if bounds["over"] == "seeds":
                merged[f"{name}_ci_low"], merged[f"{name}_ci_high"] = bounds["ci_low"], bounds["ci_high"]
            merged[f"{name}_episode_ci_low"] = bounds["episode_ci_low"]
            merged[f"{name}_episode_ci_high"] = bounds["episode_ci_high"]


def _has_stderr(metrics: Mapping[str, Any]) -> bool:
    return any(k.endswith("_stderr") or (isinstance(v, Mapping) and _has_stderr(v)) for k, v in metrics.items())


def over_seeds(per_seed: Mapping[int, Mapping[str, Any]]) -> dict[str, Any]:
    """One metrics dict for several training seeds: every number averaged over seeds, standard errors taken over
    seeds (with two or more), each per-episode list replaced by its confidence intervals, ``n_seeds`` and each seed's
    metrics under ``seeds``."""
    if not per_seed:
        raise ValueError("no training seed's metrics to aggregate")
    seeds = list(per_seed)
    values = [per_seed[s] for s in seeds]
    merged: dict[str, Any] = _mean_of(values)
    if len(seeds) > 1:
        _spread_over_seeds(merged, values)
    _intervals_in_place(merged, values)
    if _has_stderr(merged):
        merged["stderr_over"] = "seeds" if len(seeds) > 1 else "episodes"
    merged["n_seeds"] = len(seeds)
    merged["seeds"] = {str(s): dict(per_seed[s]) for s in seeds}
    return merged
