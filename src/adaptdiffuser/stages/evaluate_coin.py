"""Stage ``evaluate-coin``: a phase's planner on its family's unseen task (Maze2D: the gold coin), guided by alpha."""

from __future__ import annotations

from pathlib import Path

import mlflow
import torch

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import ConfigError, Params
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.io import read_json, write_json
from adaptdiffuser.layout import coin_metrics_path, coin_plots_dir, model_dir, reference_path
from adaptdiffuser.planning import Planner
from adaptdiffuser.stages.common import save_over_seeds
from adaptdiffuser.tooling.mlflow_logging import stage_run


def run_evaluate_coin(
    params: Params, task_name: str, root: Path, phase: int, device: torch.device, progress: bool = True
) -> dict:
    """Stage ``evaluate-coin``: :func:`evaluate_coin_seed` for every training seed; write every seed's metrics and
    their mean to ``metrics/tasks/<task>/phase<k>-coin.json``."""
    task = params.resolve(task_name)
    if task.name not in params.coin_tasks:  # evaluate-coin@phase<k> follows `evolve`, whatever its family
        skipped = {"n_episodes": 0, "skipped": f"{task.name} is not in coin_tasks (no gold-coin variant)"}
        write_json(root / coin_metrics_path(task.name, phase), skipped)
        (root / coin_plots_dir(task.name, phase, 0)).parent.mkdir(parents=True, exist_ok=True)  # the stage's output
        return skipped
    ref = read_json(root / reference_path(task.name), f"reference scores of {task.name} (run reference@{task.name})")
    unseen = get_family(task.family).unseen_task
    per_seed = {
        seed: {unseen: evaluate_coin_seed(params, task.name, root, phase, device, seed, ref, progress)}
        for seed in params.seeds
    }
    metrics = save_over_seeds(per_seed, coin_metrics_path(task.name, phase), task.name, "evaluate-coin", phase, root)
    return metrics[unseen]


def evaluate_coin_seed(
    params: Params,
    task_name: str,
    root: Path,
    phase: int,
    device: torch.device,
    seed: int,
    ref: dict,
    progress: bool = True,
) -> dict:
    """Training seed ``seed``'s model of the phase on the family's unseen task (``Family.evaluate_unseen``),
    guided by ``alpha``; its metrics are logged to MLflow with its pictures."""
    task = params.resolve(task_name)
    family = get_family(task.family)
    unseen = family.unseen_task
    if unseen is None:
        raise ConfigError(f"coin_tasks: {task.name} is of family {task.family}, which has no unseen task")
    bundle = load_bundle(root / model_dir(task.name, phase, seed), device)
    pl = task.planner
    logged = {
        unseen: task.section(unseen),
        "alpha": params.alpha,
        "planner": task.section("planner"),
        "compile": {"sampling": params.compile.sampling},
        "seed": seed,
    }
    with stage_run(task.name, "evaluate-coin", phase, logged, root, seed=seed):
        planner = Planner(bundle, make_sampler(pl.sampler, pl.sampler_steps), device, params.compile.sampling)
        pictures = root / coin_plots_dir(task.name, phase, seed)
        title = f"phase {phase} seed {seed}"
        metrics = family.evaluate_unseen(task, planner, params.alpha, ref, pictures, title, progress)
        mlflow.log_metrics({f"{unseen}.{k}": float(v) for k, v in metrics.items()})
        for picture in sorted(pictures.glob("*.png")):
            mlflow.log_artifact(str(picture), artifact_path=unseen)
    return metrics
