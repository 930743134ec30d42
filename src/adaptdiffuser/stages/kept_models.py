"""Kept models: the few trained models a headline number rests on, kept in git as EMA-only bundles and listed in
one manifest (``metrics/kept-models.json``), so that anyone can score them again on start states of their own.

A kept model's folder holds ``ema.pt``, ``normalizer.json`` and ``config.json`` (no raw weights, no optimizer);
its entry names the saved run whose ``params.yaml`` and ``reference.json`` it is evaluated under, the numbers it
supports and, for an evolved model, its equal-compute control, which :func:`evaluate_kept` plays on the same
episodes to give the paired gain."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, ValidationError

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import load_params
from adaptdiffuser.contract import TaskFiles
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.errors import StageError
from adaptdiffuser.evaluation import normalized_score, paired_gain, run_episodes, summarize
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.intervals import interval, paired_interval
from adaptdiffuser.io import read_json
from adaptdiffuser.layout import reference_path
from adaptdiffuser.planning import Planner

MANIFEST = Path("metrics/kept-models.json")


class KeptModel(BaseModel):
    """One entry of the manifest."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    #: the folder of the EMA-only bundle, relative to the repository root
    path: str
    task: str
    phase: int
    training_seed: int
    #: the evolution recipe that made its data (``plans``, ``rollouts``); None for phase 0 and controls
    recipe: str | None = None
    #: the manifest name of its equal-compute control, evaluated beside it on the same episodes
    control: str | None = None
    #: the saved run whose params.yaml and metrics/tasks/<task>/reference.json it is evaluated under
    run: str
    #: the commit whose tree first held these bytes (as a long run's carried model)
    from_commit: str
    #: the committed numbers it supports: where they are and their values
    supports: dict[str, str | float]


class Manifest(BaseModel):
    """``metrics/kept-models.json``: every tracked ``.pt`` file belongs to one of its models."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    about: str
    models: dict[str, KeptModel]


def load_manifest(root: Path) -> Manifest:
    """The manifest under ``root``; a one-line :class:`StageError` for a missing or malformed one."""
    path = root / MANIFEST
    try:
        return Manifest.model_validate(read_json(path, "the kept-models manifest"))
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(part) for part in first["loc"])
        raise StageError(f"{path}: {where}: {first['msg']}") from None


def evaluate_kept(
    root: Path,
    name: str,
    episodes: int,
    eval_seed: int,
    device: torch.device,
    progress: bool = False,
) -> dict[str, dict]:
    """Play kept model ``name`` (and its control, if it names one) on ``episodes`` episodes whose start states come
    from ``eval_seed``, under its run's params and reference scores. Returns ``{"model": metrics}``, plus
    ``{"control": metrics, "gain": paired gain}`` for a model with a control, and ``{"episode_scores": {role:
    scores}}`` (each episode's normalized score, in episode order) for intervals over several seeds."""
    manifest = load_manifest(root)
    if name not in manifest.models:
        raise StageError(f"{name}: no such kept model (listed: {', '.join(sorted(manifest.models))})")
    entry = manifest.models[name]
    scores, out = {}, {}
    for role, key in (("model", name), ("control", entry.control)):
        if key is None:
            continue
        if key not in manifest.models:
            raise StageError(f"{name}: its control {key} is not in {MANIFEST}")
        metrics, scores[role] = _play(root, manifest.models[key], episodes, eval_seed, device, progress)
        out[role] = metrics
    if "control" in scores:
        out["gain"] = paired_gain(scores["model"], scores["control"])
    out["episode_scores"] = {role: [float(x) for x in values] for role, values in scores.items()}
    return out


def _one_set(
    root: Path, names: list[str], episodes: int, seeds: dict[str, int], device: torch.device, progress: bool
) -> dict[str, dict]:
    """Every model of ``names`` (and its control) on its start states ``seeds[name]``, and the intervals over them."""
    runs = {name: evaluate_kept(root, name, episodes, seeds[name], device, progress) for name in names}
    scores = [runs[name]["episode_scores"]["model"] for name in names]
    summary: dict[str, dict] = {"score": interval(scores)}
    if all("control" in runs[name]["episode_scores"] for name in names):
        controls = [runs[name]["episode_scores"]["control"] for name in names]
        summary |= {"control": interval(controls), "gain": paired_interval(scores, controls)}
    return {"models": runs, "eval_seeds": seeds, "interval": summary}


def evaluate_kept_seeds(
    root: Path,
    names: list[str],
    episodes: int,
    eval_seed: int,
    device: torch.device,
    own_start_states: bool = True,
    progress: bool = False,
    held_out_seed: int | None = None,
    held_out_episodes: int | None = None,
) -> dict[str, dict]:
    """:func:`evaluate_kept` for several kept models (one per training seed, say), each on start states of its own:
    those of ``eval_seed + its training seed`` (``own_start_states``; else all on ``eval_seed``'s). Returns
    ``{"models": {name: its evaluation}, "eval_seeds": {name: seed}}`` and, over the models, ``"interval"``: the mean
    and 95 % intervals (:func:`adaptdiffuser.intervals.interval`: over seeds, a t-interval of the models' means; with
    one model over episodes) of the score, and where every model has a control, of the control's score and of the
    paired gain with its win rate. With ``held_out_seed``, the same again on a held-out set (``held_out_seed`` +
    training seed, ``held_out_episodes`` episodes, default ``episodes``; 0: none) under ``"held_out"``; the two sets
    must not share a start state."""
    manifest = load_manifest(root)
    if len(set(names)) != len(names):
        raise StageError(f"a kept model named twice among {names}: each counts once in the interval")
    missing = [name for name in names if name not in manifest.models]
    if missing:
        raise StageError(f"{missing[0]}: no such kept model (listed: {', '.join(sorted(manifest.models))})")

    def seeds_of(base: int) -> dict[str, int]:
        return {name: base + (manifest.models[name].training_seed if own_start_states else 0) for name in names}

    seeds = seeds_of(eval_seed)
    plays_held_out = held_out_seed is not None and held_out_episodes != 0
    if held_out_seed is not None and plays_held_out:
        shared = set(seeds.values()) & set(seeds_of(held_out_seed).values())
        if shared:
            raise StageError(
                f"held-out seed {held_out_seed} and evaluation seed {eval_seed} both give start states of seed "
                f"{min(shared)} to these models; choose held-out start states that are others"
            )
    out = _one_set(root, names, episodes, seeds, device, progress)
    if held_out_seed is not None and plays_held_out:
        held_out = held_out_episodes if held_out_episodes is not None else episodes
        out["held_out"] = {"episodes": held_out} | _one_set(
            root, names, held_out, seeds_of(held_out_seed), device, progress
        )
    return out


def _play(
    root: Path, entry: KeptModel, episodes: int, eval_seed: int, device: torch.device, progress: bool
) -> tuple[dict[str, float | int], np.ndarray]:
    """One kept model's metrics and per-episode scores on the given episodes."""
    run = root / entry.run
    # the run's record may predate evaluation keys added since; this evaluation sets its own episodes and seed
    params = load_params(run / "params.yaml", set_by_caller=("evaluate.",))
    task = params.resolve(entry.task)
    task = dataclasses.replace(
        task, evaluate=dataclasses.replace(task.evaluate, episodes=episodes, seed=eval_seed, pictures=0)
    )
    ref = read_json(run / reference_path(entry.task), f"reference scores of {entry.task} in {entry.run}")
    family = get_family(task.family)
    bundle = load_bundle(root / entry.path, device, ema_only=True)
    sampler = make_sampler(task.planner.sampler, task.planner.sampler_steps)
    planner = Planner(bundle, sampler, device, params.compile.sampling)
    files = TaskFiles(root, entry.task, Path(entry.path), entry.training_seed)
    controller = family.controller(task, planner, files, device)
    result = run_episodes(
        lambda: family.make_simulator(task),
        controller,
        episodes,
        eval_seed,
        task.evaluate.batch_size,
        desc=f"evaluate kept {entry.path}",
        progress=progress,
    )
    metrics = summarize(result, ref["r_min"], ref["r_max"]) | family.episode_metrics(result)
    return metrics, np.asarray(normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"]))
