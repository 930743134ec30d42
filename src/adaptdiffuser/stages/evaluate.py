"""Stages ``evaluate`` and ``evaluate-control``: a phase's planner (or its equal-compute control's) on a task under
its protocol; results, pictures and metrics, and for a control the paired gain of the phase over it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import Params, TaskParams
from adaptdiffuser.contract import EpisodeBatchResult, TaskFiles
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.errors import StageError
from adaptdiffuser.evaluation import normalized_score, paired_gain, run_episodes, summarize
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.io import atomic_path, read_json
from adaptdiffuser.layout import (
    HELD_OUT,
    model_dir,
    phase_metrics_path,
    phase_name,
    plots_dir,
    reference_path,
    results_dir,
    seed_record_dir,
)
from adaptdiffuser.planning import Planner
from adaptdiffuser.stages.common import save_over_seeds
from adaptdiffuser.stages.seed_records import each_seed, evaluation_key, remove_records
from adaptdiffuser.stages.training_data import code_digest
from adaptdiffuser.tooling.run_records import stage_run


def run_evaluate(
    params: Params,
    task_name: str,
    root: Path,
    phase: int,
    device: torch.device,
    progress: bool = True,
    control: bool = False,
) -> dict:
    """Stage ``evaluate`` (or ``evaluate-control``): :func:`evaluate_seed` for every training seed, each on its own
    start states; write the metrics of every seed and their aggregate (mean and standard error over seeds, and
    confidence intervals from every seed's episodes; see :mod:`adaptdiffuser.seed_metrics`) to
    ``metrics/tasks/<task>/phase<k>[-control].json``. A seed evaluated by an interrupted earlier run of the stage,
    with the same settings, model and code, is taken from its record
    (:mod:`adaptdiffuser.stages.seed_records`) instead of being played again."""
    task = params.resolve(task_name)
    ref = read_json(root / reference_path(task.name), f"reference scores of {task.name} (run reference@{task.name})")
    code = code_digest(root, task.name)

    def record(seed: int) -> Path:
        return seed_record_dir(task.name, "evaluate", phase, seed, control)

    def key(seed: int) -> str:
        tables = (
            ("episodes.parquet", f"{HELD_OUT}.parquet") if task.evaluate.held_out_episodes else ("episodes.parquet",)
        )
        evolved = [root / results_dir(task.name, phase, seed) / table for table in tables] if control else []
        model = root / model_dir(task.name, phase, seed, control)
        return evaluation_key(_settings(params, task, seed), ref, code, model=model, files=evolved)

    per_seed = each_seed(
        root,
        params.seeds,
        record,
        key,
        lambda seed: [results_dir(task.name, phase, seed, control), plots_dir(task.name, phase, seed, control)],
        lambda seed: evaluate_seed(params, task.name, root, phase, device, seed, ref, progress, control),
    )
    stage = "evaluate-control" if control else "evaluate"
    path = phase_metrics_path(task.name, phase, control)
    metrics = save_over_seeds(per_seed, path, task.name, stage, phase, root)
    remove_records(root, map(record, params.seeds))
    return metrics


def _settings(params: Params, task: TaskParams, seed: int) -> dict:
    """What decides one seed's evaluation besides its model, its code and the reference scores."""
    return {
        "task": task.section("settings"),
        "planner": task.section("planner"),
        "evaluate": task.section("evaluate"),
        "compile": {"sampling": params.compile.sampling},
        "seed": seed,
    }


def evaluate_seed(
    params: Params,
    task_name: str,
    root: Path,
    phase: int,
    device: torch.device,
    seed: int,
    ref: dict,
    progress: bool = True,
    control: bool = False,
) -> dict:
    """Run training seed ``seed``'s planner of phase ``phase`` on its own start states (``evaluate.seed`` + seed),
    then on its held-out ones (``evaluate.held_out_seed`` + seed, under ``held_out``); write each per-episode table
    (``episodes.parquet``, ``held_out.parquet``) and pictures of the first episodes; return the metrics: score mean
    and standard error over episodes, and each episode's score (``score_per_episode``, from which the aggregate over
    seeds takes its confidence interval).

    With ``control``, evaluate phase k's control model on the same episodes instead, and add on each set the gain of
    phase k over it, paired over episodes (``gain_mean``, ``gain_stderr``, ``gain_per_episode`` and ``win_rate``;
    phase k's evaluation must exist)."""
    task = params.resolve(task_name)
    family = get_family(task.family)
    model = model_dir(task.name, phase, seed, control)
    bundle = load_bundle(root / model, device)
    evolved_dir = root / results_dir(task.name, phase, seed)
    if control and not (evolved_dir / "episodes.parquet").exists():
        raise FileNotFoundError(
            f"{evolved_dir / 'episodes.parquet'}: phase {phase}'s evaluation, needed for the gain over its control"
        )
    ev, pl = task.evaluate, task.planner
    logged = _settings(params, task, seed) | {"model": {"path": str(model), "data": bundle.config.get("data", {})}}
    name = phase_name(phase, control)
    out_dir = root / results_dir(task.name, phase, seed, control)
    with stage_run(task.name, "evaluate-control" if control else "evaluate", phase, logged, root, seed=seed) as run:
        files = TaskFiles(root, task.name, model, seed)
        planner = Planner(bundle, make_sampler(pl.sampler, pl.sampler_steps), device, params.compile.sampling)
        controller = family.controller(task, planner, files, device)

        def play(episodes: int, start_seed: int, table_name: str, prefix: str) -> tuple[dict, EpisodeBatchResult]:
            """One set of start states: its metrics (paired with phase k's on them for a control) and episodes."""
            result = run_episodes(
                lambda: family.make_simulator(task),
                controller,
                episodes,
                start_seed,
                ev.batch_size,
                desc=f"evaluate {task.name} {name} seed {seed}" + (f" ({prefix.strip('.')})" if prefix else ""),
                progress=progress,
            )
            metrics = summarize(result, ref["r_min"], ref["r_max"]) | family.episode_metrics(result)
            scores = normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"])
            table = pa.table(
                {
                    "episode": result.episodes,
                    "return": result.returns,
                    "score": scores,
                    "length": result.lengths,
                    "terminated": result.terminated,
                    **family.episode_columns(result),
                }
            )
            lists = {"score_per_episode": [float(x) for x in scores]}
            if control:
                gain, lists["gain_per_episode"] = _gain_over(evolved_dir / table_name, result.episodes, scores, phase)
                metrics |= gain
            run.log_metrics({f"{prefix}{k}": float(v) for k, v in metrics.items()})
            out = out_dir / table_name
            out.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(out) as tmp:
                pq.write_table(table, tmp)
            run.log_artifact(str(out))
            return metrics | lists, result

        metrics, result = play(ev.episodes, ev.seed + seed, "episodes.parquet", "")
        if ev.held_out_episodes:
            held_out, _ = play(ev.held_out_episodes, ev.held_out_seed + seed, f"{HELD_OUT}.parquet", f"{HELD_OUT}.")
            metrics[HELD_OUT] = held_out
        pictures = root / plots_dir(task.name, phase, seed, control)
        for i in range(min(ev.pictures, ev.episodes)):
            picture = pictures / f"plan_{i:02d}.png"
            score = normalized_score(result.returns[i], ref["r_min"], ref["r_max"])
            title = f"{task.name} {name} seed {seed}, episode {i}: return {result.returns[i]:.0f}, score {score:.0f}"
            family.save_picture(task, picture, result.plans[i], result.executed[i], title, goal=result.goals[i])
            run.log_artifact(str(picture), artifact_path="plans")
    return metrics


def _gain_over(
    evolved_table: Path, episodes: list[int], scores: np.ndarray, phase: int
) -> tuple[dict[str, float | int], list[float]]:
    """The gain of phase k (its table of the same start states) over its control's ``scores``, paired over
    episodes: mean, standard error and the win rate (the share of episodes phase k scores above its control, ties
    half); and each episode's."""
    evolved = pq.read_table(evolved_table, columns=["episode", "score"]).to_pydict()
    if evolved["episode"] != list(episodes):
        raise StageError(f"{evolved_table}: its episodes differ from the control's; rerun evaluate@phase{phase}")
    diff = np.asarray(evolved["score"]) - scores
    return paired_gain(np.asarray(evolved["score"]), scores), [float(x) for x in diff]
