"""Stage ``evaluate``: a phase's planner on a task under its protocol; results, pictures and metrics."""

from __future__ import annotations

from pathlib import Path

import mlflow
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import Params
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.evaluation import normalized_score, run_episodes, summarize
from adaptdiffuser.families.base import TaskFiles
from adaptdiffuser.families.registry import get_family
from adaptdiffuser.io import atomic_path, read_json, write_json
from adaptdiffuser.planning import Planner
from adaptdiffuser.stages.common import model_dir, phase_metrics_path, plots_dir, reference_path, results_dir
from adaptdiffuser.tracking import stage_run


def run_evaluate(
    params: Params, task_name: str, root: Path, phase: int, device: torch.device, progress: bool = True
) -> dict:
    """Stage ``evaluate``: run phase ``phase``'s planner on the task's evaluation episodes (batched), write the
    per-episode table, pictures of the first episodes and the metrics (score mean and standard error)."""
    task = params.resolve(task_name)
    family = get_family(task.family)
    ref = read_json(root / reference_path(task.name), f"reference scores of {task.name} (run reference@{task.name})")
    bundle = load_bundle(root / model_dir(task.name, phase), device)
    ev, pl = task.evaluate, task.planner
    logged = {
        "task": task.section("settings"),
        "planner": task.section("planner"),
        "evaluate": task.section("evaluate"),
        "model": {"path": str(model_dir(task.name, phase)), "data": bundle.config.get("data", {})},
    }
    with stage_run(task.name, "evaluate", phase, logged, root):
        files = TaskFiles(root, task.name)
        planner = Planner(bundle, make_sampler(pl.sampler, pl.sampler_steps), device)
        controller = family.controller(task, planner, files, device)
        result = run_episodes(
            lambda: family.make_simulator(task),
            controller,
            ev.episodes,
            ev.seed,
            ev.batch_size,
            desc=f"evaluate {task.name} phase {phase}",
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
        out = root / results_dir(task.name, phase) / "episodes.parquet"
        out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(out) as tmp:
            pq.write_table(table, tmp)
        pictures = root / plots_dir(task.name, phase)
        for i in range(min(ev.pictures, ev.episodes)):
            picture = pictures / f"plan_{i:02d}.png"
            title = f"{task.name} phase {phase}, episode {i}: return {result.returns[i]:.0f}, score {scores[i]:.0f}"
            family.save_picture(task, picture, result.plans[i], result.executed[i], title, goal=result.goals[i])
            mlflow.log_artifact(str(picture), artifact_path="plans")
        write_json(root / phase_metrics_path(task.name, phase), metrics)
        mlflow.log_metrics({k: float(v) for k, v in metrics.items()})
        mlflow.log_artifact(str(out))
    return metrics
