"""Stage ``summarize``: every task's per-phase metrics merged into ``metrics/summary.json``."""

from __future__ import annotations

from pathlib import Path

from adaptdiffuser.config import Params
from adaptdiffuser.io import read_json, write_json
from adaptdiffuser.stages.common import (
    SUMMARY,
    coin_metrics_path,
    discriminator_metrics_path,
    phase_metrics_path,
    reference_path,
)

SUMMARY_DISCRIMINATOR_KEYS = ("generated", "kept", "kept_fraction", "tracking_error_mean")
GAIN_KEYS = ("gain_mean", "gain_stderr")


def task_phases(params: Params, task: str) -> list[int]:
    """The phases a task is evaluated at: 0, and 1..K for the evolved task."""
    return [0, *(phase.index for phase in params.phases)] if task == params.evolve else [0]


def run_summarize(params: Params, root: Path) -> dict:
    """``{task: {"dataset": {...}?, "phase_k": {score_mean, score_stderr, ..., gain_mean?, gain_stderr?,
    "control"?, "discriminator"?}}}``: each phase's evaluation metrics, its gold-coin metrics where the task has
    them; for evolution phases the discriminator counts, the equal-compute control's metrics and the gain of the
    phase over it (paired over episodes); and the dataset's own score where the reference stage measured it."""
    summary: dict[str, dict] = {}
    for task in params.tasks:
        entry: dict[str, dict] = {}
        ref = read_json(root / reference_path(task), f"reference of {task} (run reference@{task})")
        if "dataset" in ref:
            entry["dataset"] = ref["dataset"]
        for k in task_phases(params, task):
            phase = read_json(root / phase_metrics_path(task, k), f"metrics of {task} phase {k} (run its evaluate)")
            if task in params.coin_tasks:
                coin = read_json(root / coin_metrics_path(task, k), f"gold-coin metrics of {task} phase {k}")
                phase.update(coin)
            if k > 0:
                report = read_json(root / discriminator_metrics_path(task, k), f"discriminator report of phase {k}")
                phase["discriminator"] = {key: report[key] for key in SUMMARY_DISCRIMINATOR_KEYS}
                control = read_json(
                    root / phase_metrics_path(task, k, control=True), f"metrics of {task} phase {k}'s control"
                )
                phase.update({key: control.pop(key) for key in GAIN_KEYS})
                phase["control"] = {key: value for key, value in control.items() if not key.startswith("gain_")}
            entry[f"phase_{k}"] = phase
        summary[task] = entry
    write_json(root / SUMMARY, summary)
    return summary
