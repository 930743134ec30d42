"""Stages ``evaluate-unseen`` and ``evaluate-unseen-control``: a phase's planner (or its equal-compute control's) on
its family's unseen task (Maze2D: the gold coin; KUKA: pick-and-place), guided with the top-level ``alpha``."""

from __future__ import annotations

from pathlib import Path

import torch

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import ConfigError, Params, TaskParams
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.io import read_json, write_json
from adaptdiffuser.layout import model_dir, reference_path, seed_record_dir, unseen_metrics_path, unseen_plots_dir
from adaptdiffuser.planning import Planner
from adaptdiffuser.stages.common import save_over_seeds
from adaptdiffuser.stages.seed_records import each_seed, evaluation_key, remove_records
from adaptdiffuser.stages.training_data import code_digest
from adaptdiffuser.tooling.run_records import stage_run


def stage_name(control: bool) -> str:
    return "evaluate-unseen-control" if control else "evaluate-unseen"


def run_evaluate_unseen(
    params: Params,
    task_name: str,
    root: Path,
    phase: int,
    device: torch.device,
    progress: bool = True,
    control: bool = False,
) -> dict:
    """:func:`evaluate_unseen_seed` for every training seed; write every seed's metrics and their mean to
    ``metrics/tasks/<task>/phase<k>[-control]-unseen.json`` (``{<unseen task>: metrics, ...}``) and return the
    mean's metrics (a seed that an interrupted earlier run evaluated alike is taken from its record, as in
    ``evaluate``). A task outside ``unseen_tasks`` (its family has no unseen task) gets a file saying so."""
    task = params.resolve(task_name)
    if task.name not in params.unseen_tasks:  # the phases' stages follow `evolve`, whatever its family
        skipped = {"n_episodes": 0, "skipped": f"{task.name} is not in unseen_tasks (its family has no unseen task)"}
        write_json(root / unseen_metrics_path(task.name, phase, control), skipped)
        (root / unseen_plots_dir(task.name, phase, 0, control)).parent.mkdir(parents=True, exist_ok=True)
        return skipped
    ref = read_json(root / reference_path(task.name), f"reference scores of {task.name} (run reference@{task.name})")
    unseen = get_family(task.family).unseen_task
    code = code_digest(root, task.name)

    def record(seed: int) -> Path:
        return seed_record_dir(task.name, "evaluate-unseen", phase, seed, control)

    def key(seed: int) -> str:
        model = root / model_dir(task.name, phase, seed, control)
        settings = _settings(params, task, unseen, seed) | {"task": task.section("settings")}  # all of the family's
        return evaluation_key(settings, ref, code, model=model)

    per_seed = each_seed(
        root,
        params.seeds,
        record,
        key,
        lambda seed: [unseen_plots_dir(task.name, phase, seed, control)],
        lambda seed: {
            unseen: evaluate_unseen_seed(params, task.name, root, phase, device, seed, ref, progress, control)
        },
    )
    path = unseen_metrics_path(task.name, phase, control)
    metrics = save_over_seeds(per_seed, path, task.name, stage_name(control), phase, root)
    remove_records(root, map(record, params.seeds))
    return metrics[unseen]


def _settings(params: Params, task: TaskParams, unseen: str, seed: int) -> dict:
    """What decides one seed's evaluation on the unseen task besides its model, its code and the reference scores."""
    return {
        unseen: task.section(unseen),
        "alpha": params.alpha,
        "planner": task.section("planner"),
        "compile": {"sampling": params.compile.sampling},
        "seed": seed,
    }


def evaluate_unseen_seed(
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
    """Training seed ``seed``'s model of the phase (or of its control) on the family's unseen task
    (``Family.evaluate_unseen``), guided by ``alpha``; its metrics are logged to MLflow with its pictures."""
    task = params.resolve(task_name)
    family = get_family(task.family)
    unseen = family.unseen_task
    if unseen is None:
        raise ConfigError(f"unseen_tasks: {task.name} is of family {task.family}, which has no unseen task")
    bundle = load_bundle(root / model_dir(task.name, phase, seed, control), device)
    pl = task.planner
    logged = _settings(params, task, unseen, seed)
    with stage_run(task.name, stage_name(control), phase, logged, root, seed=seed) as run:
        planner = Planner(bundle, make_sampler(pl.sampler, pl.sampler_steps), device, params.compile.sampling)
        pictures = root / unseen_plots_dir(task.name, phase, seed, control)
        pictures.mkdir(parents=True, exist_ok=True)  # the stage's output, also for a family that draws none
        title = f"phase {phase}{' control' if control else ''} seed {seed}"
        metrics = family.evaluate_unseen(task, planner, params.alpha, ref, pictures, title, progress)
        measured = {k: v for k, v in metrics.items() if v is not None}  # None: no episode to measure it on
        run.log_metrics({f"{unseen}.{k}": float(v) for k, v in measured.items()})
        for picture in sorted(pictures.glob("*.png")):
            run.log_artifact(str(picture), artifact_path=unseen)
    return metrics
