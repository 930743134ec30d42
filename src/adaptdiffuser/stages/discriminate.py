"""Stage ``discriminate@phase<k>``: track the generated plans in the simulator, reject and select."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import mlflow

from adaptdiffuser.config import Params
from adaptdiffuser.data.schema import read_trajectories, write_trajectories
from adaptdiffuser.evolution.discriminator import NothingSelectedError
from adaptdiffuser.families.base import TaskFiles
from adaptdiffuser.families.registry import get_family
from adaptdiffuser.plots import save_discriminator_histograms
from adaptdiffuser.stages.common import (
    discriminator_metrics_path,
    discriminator_plot_path,
    file_digest,
    generated_path,
    save_over_seeds,
    selected_path,
)
from adaptdiffuser.tracking import stage_run


def run_discriminate(params: Params, task_name: str, root: Path, phase: int, progress: bool = True) -> dict:
    """Stage ``discriminate@phase<k>``: :func:`discriminate_seed` for every training seed; write the reports,
    with their mean over seeds, to ``metrics/tasks/<task>/phase<k>-discriminator.json``."""
    task = params.resolve(task_name)
    reports = {seed: discriminate_seed(params, task.name, root, phase, seed, progress) for seed in params.seeds}
    return save_over_seeds(
        reports, discriminator_metrics_path(task.name, phase), task.name, "discriminate", phase, root
    )


def discriminate_seed(params: Params, task_name: str, root: Path, phase: int, seed: int, progress: bool = True) -> dict:
    """Judge ``data/<task>/phase<k>/generated/seed<s>.parquet``; write the kept executed trajectories to
    ``data/<task>/phase<k>/selected/seed<s>.parquet`` and histograms to ``plots/``; return the report.

    Raises :class:`NothingSelectedError` (and writes no dataset) when nothing is kept."""
    task = params.resolve(task_name)
    cfg = params.phase(phase).discriminate
    source = root / generated_path(task.name, phase, seed)
    generated = read_trajectories(source, env=task.name)
    logged = {
        "discriminate": asdict(cfg),
        "seed": seed,
        "data": {"generated": {"path": str(generated_path(task.name, phase, seed)), "sha256": file_digest(source)}},
        "planner": {
            "tracking_p_gain": task.planner.tracking_p_gain,
            "tracking_d_gain": task.planner.tracking_d_gain,
        },
    }
    with stage_run(task.name, "discriminate", phase, logged, root, seed=seed):
        family = get_family(task.family)
        files = TaskFiles(root, task.name, seed=seed)
        judgement = family.discriminate(task, generated, cfg, phase, files, progress)
        report = judgement.report()
        mlflow.log_metrics({f"discriminator.{k}": float(v) for k, v in report.items()})
        picture = root / discriminator_plot_path(task.name, phase, seed)
        save_discriminator_histograms(
            judgement,
            cfg.max_error,
            picture,
            f"phase {phase}, seed {seed}: {report['kept']} of {report['generated']} kept",
        )
        mlflow.log_artifact(str(picture), artifact_path="discriminator")
        if not len(judgement.kept):
            raise NothingSelectedError(
                f"phase {phase}, training seed {seed}: the discriminator kept none of {report['generated']} "
                "generated trajectories "
                f"({report['rejected_tracking']} failed tracking with max_error={cfg.max_error}, "
                f"{report['rejected_reward']} failed the {cfg.rule!r} rule); not fine-tuning on nothing. "
                "Loosen evolution.discriminate (max_error, rule: quantile) or generate more tasks."
            )
        generator = {
            "stage": "discriminate",
            "phase": phase,
            "training_seed": seed,
            "source": str(generated_path(task.name, phase, seed)),
            **asdict(cfg),
        }
        selected = family.selected_data(task, generated, judgement, generator)
        write_trajectories(root / selected_path(task.name, phase, seed), selected)
    return report
