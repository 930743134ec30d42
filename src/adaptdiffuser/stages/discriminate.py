"""Stage ``discriminate@phase<k>``: track the generated plans in the simulator, reject and select."""

from __future__ import annotations

import sys
from dataclasses import asdict, replace
from pathlib import Path

from adaptdiffuser.config import Params
from adaptdiffuser.contract import TaskFiles
from adaptdiffuser.data.schema import Trajectories, read_trajectories, write_trajectories
from adaptdiffuser.data.windows import take_episodes
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.layout import discriminator_metrics_path, discriminator_plot_path, generated_path, selected_path
from adaptdiffuser.plots import save_discriminator_histograms
from adaptdiffuser.stages.common import file_digest, save_over_seeds
from adaptdiffuser.tooling.run_records import stage_run


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

    When nothing is kept that is the phase's result, not an error: one warning line, ``kept`` 0 in the report, and
    a selected file with no rows (fine-tuning then trains on what earlier phases selected, or, with nothing at
    all, exactly as the phase's equal-compute control)."""
    task = params.resolve(task_name)
    cfg = params.phase(phase).discriminate
    source = root / generated_path(task.name, phase, seed)
    generated = read_trajectories(source, env=task.name)
    logged = {
        "discriminate": asdict(cfg),
        "seed": seed,
        "data": {"generated": {"path": str(generated_path(task.name, phase, seed)), "sha256": file_digest(source)}},
    }
    with stage_run(task.name, "discriminate", phase, logged, root, seed=seed) as run:
        family = get_family(task.family)
        files = TaskFiles(root, task.name, seed=seed)
        judgement = family.discriminate(task, generated, cfg, phase, files, progress)
        report = judgement.report()
        run.log_metrics({f"discriminator.{k}": float(v) for k, v in report.items()})
        picture = root / discriminator_plot_path(task.name, phase, seed)
        save_discriminator_histograms(
            judgement,
            cfg.max_error,
            picture,
            f"phase {phase}, seed {seed}: {report['kept']} of {report['generated']} kept",
        )
        run.log_artifact(str(picture), artifact_path="discriminator")
        generator = {
            "stage": "discriminate",
            "phase": phase,
            "training_seed": seed,
            "source": str(generated_path(task.name, phase, seed)),
            **asdict(cfg),
        }
        if len(judgement.kept):
            selected = family.selected_data(task, generated, judgement, generator)
        else:
            print(
                f"warning: {task.name} phase {phase}, training seed {seed}: the discriminator kept none of "
                f"{report['generated']} generated trajectories ({report['rejected_tracking']} failed tracking with "
                f"max_error={cfg.max_error}, {report['rejected_reward']} failed the {cfg.rule!r} rule); the phase "
                "fine-tunes on earlier phases' selections only (none: it is its equal-compute control)",
                file=sys.stderr,
                flush=True,
            )
            selected = no_rows(generated, generator)
        write_trajectories(root / selected_path(task.name, phase, seed), selected)
    return report


def no_rows(generated: Trajectories, generator: dict) -> Trajectories:
    """An empty selection: ``generated``'s columns with no rows, its metadata naming this stage as generator."""
    return replace(take_episodes(generated, []), metadata={**generated.metadata, "generator": generator})
