"""Stages ``evaluate`` and ``evaluate-control``: a phase's planner (or its equal-compute control's) on a task under
its protocol; results, pictures and metrics, and for a control the paired gain of the phase over it."""

from __future__ import annotations

from pathlib import Path

import mlflow
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import Params, TaskParams
from adaptdiffuser.contract import TaskFiles
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.errors import StageError
from adaptdiffuser.evaluation import normalized_score, paired_gain, run_episodes, summarize
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.io import atomic_path, read_json
from adaptdiffuser.layout import (
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
from adaptdiffuser.tooling.mlflow_logging import stage_run


def run_evaluate(
    params: Params,
    task_name: str,
    root: Path,
    phase: int,
    device: torch.device,
    progress: bool = True,
    control: bool = False,
) -> dict:
    """Stage ``evaluate`` (or ``evaluate-control``): :func:`evaluate_seed` for every training seed, on the same
    episodes; write the metrics of every seed and their aggregate (mean and standard error over seeds; see
    :mod:`adaptdiffuser.seed_metrics`) to ``metrics/tasks/<task>/phase<k>[-control].json``. A seed evaluated by an
    interrupted earlier run of the stage, with the same settings, model and code, is taken from its record
    (:mod:`adaptdiffuser.stages.seed_records`) instead of being played again."""
    task = params.resolve(task_name)
    ref = read_json(root / reference_path(task.name), f"reference scores of {task.name} (run reference@{task.name})")
    code = code_digest(root, task.name)

    def record(seed: int) -> Path:
        return seed_record_dir(task.name, "evaluate", phase, seed, control)

    def key(seed: int) -> str:
        evolved = [root / results_dir(task.name, phase, seed) / "episodes.parquet"] if control else []
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
    """Run training seed ``seed``'s planner of phase ``phase`` on the task's evaluation episodes (batched); write
    the per-episode table and pictures of the first episodes; return the metrics (score mean and standard error
    over episodes).

    With ``control``, evaluate phase k's control model on the same episodes instead, and add the gain of phase k
    over it (``gain_mean``, ``gain_stderr``: paired over episodes; phase k's evaluation must exist)."""
    task = params.resolve(task_name)
    family = get_family(task.family)
    model = model_dir(task.name, phase, seed, control)
    bundle = load_bundle(root / model, device)
    evolved_table = root / results_dir(task.name, phase, seed) / "episodes.parquet"
    if control and not evolved_table.exists():
        raise FileNotFoundError(f"{evolved_table}: phase {phase}'s evaluation, needed for the gain over its control")
    ev, pl = task.evaluate, task.planner
    logged = _settings(params, task, seed) | {"model": {"path": str(model), "data": bundle.config.get("data", {})}}
    name = phase_name(phase, control)
    with stage_run(task.name, "evaluate-control" if control else "evaluate", phase, logged, root, seed=seed):
        files = TaskFiles(root, task.name, model, seed)
        planner = Planner(bundle, make_sampler(pl.sampler, pl.sampler_steps), device, params.compile.sampling)
        controller = family.controller(task, planner, files, device)
        result = run_episodes(
            lambda: family.make_simulator(task),
            controller,
            ev.episodes,
            ev.seed,
            ev.batch_size,
            desc=f"evaluate {task.name} {name} seed {seed}",
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
        if control:
            evolved = pq.read_table(evolved_table, columns=["episode", "score"]).to_pydict()
            if evolved["episode"] != result.episodes:
                raise StageError(
                    f"{evolved_table}: its episodes differ from the control's; rerun evaluate@phase{phase}"
                )
            metrics |= paired_gain(np.asarray(evolved["score"]), scores)
        out = root / results_dir(task.name, phase, seed, control) / "episodes.parquet"
        out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(out) as tmp:
            pq.write_table(table, tmp)
        pictures = root / plots_dir(task.name, phase, seed, control)
        for i in range(min(ev.pictures, ev.episodes)):
            picture = pictures / f"plan_{i:02d}.png"
            title = (
                f"{task.name} {name} seed {seed}, episode {i}: return {result.returns[i]:.0f}, score {scores[i]:.0f}"
            )
            family.save_picture(task, picture, result.plans[i], result.executed[i], title, goal=result.goals[i])
            mlflow.log_artifact(str(picture), artifact_path="plans")
        mlflow.log_metrics({k: float(v) for k, v in metrics.items()})
        mlflow.log_artifact(str(out))
    return metrics
