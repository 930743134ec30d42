"""Stage ``summarize``: every task's per-phase metrics merged into ``metrics/summary.json``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from adaptdiffuser.config import Params
from adaptdiffuser.config.params import unseen_task_of
from adaptdiffuser.evaluation import standard_error
from adaptdiffuser.io import read_json, write_json
from adaptdiffuser.layout import (
    HELD_OUT,
    SUMMARY,
    discriminator_metrics_path,
    phase_metrics_path,
    reference_path,
    unseen_metrics_path,
)
from adaptdiffuser.stages.common import GAIN_KEYS, phase_entries, unseen_scores
from adaptdiffuser.tooling.run_records import stage_run

SUMMARY_DISCRIMINATOR_KEYS = ("generated", "kept", "kept_fraction", "tracking_error_mean", "return_mean_kept")
PER_SEED_KEYS = ("score_mean", "score_stderr", "gain_mean", "gain_stderr")
#: what 0 and 100 of the score mean, and other constants to read it on where the reference gives them (D4RL's)
REFERENCE_KEYS = ("r_min", "r_max", "d4rl_r_min", "d4rl_r_max")


def _without_seeds(metrics: dict) -> dict:
    """A metrics file's aggregate over training seeds (its ``seeds`` entry removed)."""
    return {key: value for key, value in metrics.items() if key != "seeds"}


def _per_seed(metrics: dict, control: dict | None) -> dict[str, dict]:
    """Each training seed's score (and gain over its control), for the report's per-seed points."""
    out = {}
    for seed, m in metrics.get("seeds", {}).items():
        row = {k: m[k] for k in PER_SEED_KEYS if k in m}
        if control is not None:
            c = control["seeds"][seed]
            row |= {"control_score_mean": c["score_mean"], **{k: c[k] for k in GAIN_KEYS if k in c}}
        out[seed] = row
    return out


def _unseen_file(root: Path, task: str, phase: int, unseen: str, control: bool) -> dict:
    """A phase's (or its control's) metrics file of the unseen task ``unseen``: the mean over training seeds under
    ``unseen`` and each seed's under ``seeds``."""
    who = f"{task} phase {phase}" + ("'s control" if control else "")
    return read_json(root / unseen_metrics_path(task, phase, control), f"{unseen} metrics of {who}")


def unseen_gain(phase: dict, control: dict, unseen: str) -> dict[str, dict]:
    """The gain of a phase over its control on the unseen task, seed by seed (the same training seed's phase and
    control): for every score of ``unseen`` (``score_mean`` and, e.g., KUKA's ``setup1_score_mean``), keyed by its
    name without ``_mean``, ``{"gain_mean", "gain_stderr", "per_seed"}``; the standard error is over training seeds,
    None with one seed."""
    seeds = [seed for seed in phase.get("seeds", {}) if seed in control.get("seeds", {})]
    gains = {}
    for score in unseen_scores(phase[unseen]):
        key = f"{score}_mean"
        diffs = {s: phase["seeds"][s][unseen][key] - control["seeds"][s][unseen][key] for s in seeds}
        if not diffs:
            continue
        values = list(diffs.values())
        gains[score] = {
            "gain_mean": float(sum(values) / len(values)),
            "gain_stderr": standard_error(values) if len(values) > 1 else None,
            "per_seed": diffs,
        }
    return gains


def _gain_moved(phase: dict, control: dict) -> dict:
    """The control's metrics without its gain keys, which go to ``phase`` (the gain is the phase's), on the main
    start states and on the held-out ones alike."""
    phase.update({key: control[key] for key in GAIN_KEYS if key in control})
    rest = {key: value for key, value in control.items() if key not in GAIN_KEYS and not key.startswith("gain_")}
    if isinstance(control.get(HELD_OUT), dict) and isinstance(phase.get(HELD_OUT), dict):
        rest[HELD_OUT] = _gain_moved(phase[HELD_OUT], control[HELD_OUT])
    return rest


def task_phases(params: Params, task: str) -> list[int]:
    """The phases a task is evaluated at: 0, and 1..K for the evolved task."""
    return [0, *(phase.index for phase in params.phases)] if task == params.evolve else [0]


def run_summarize(params: Params, root: Path) -> dict:
    """The summary of :func:`build_summary`, written to ``metrics/summary.json`` and logged to MLflow (a run per
    task), with every pending run record of the pipeline run (see
    :func:`~adaptdiffuser.tooling.mlflow_logging.log_pending`)."""
    summary = build_summary(params, root)
    write_json(root / SUMMARY, summary)
    try:
        for task, entry in summary.items():
            log_evolution(task, entry, root)
    finally:  # the pipeline run's last stage logs its stages' run records to MLflow, this one's included
        from adaptdiffuser.tooling.mlflow_logging import log_pending

        log_pending(root)
    return summary


def build_summary(params: Params, root: Path) -> dict:
    """``{task: {"reference": {...}, "dataset": {...}?, "unseen_task"?, "phase_k": {score_mean, score_stderr, ...,
    gain_mean?, gain_stderr?, <unseen task>?, "unseen_gain"?, "control"?, "discriminator"?, "per_seed"}}}``: each
    phase's evaluation metrics; the task's reference constants (``reference``: R_min, R_max, and D4RL's where the family
    gives them); for tasks of ``unseen_tasks``, the name of their family's unseen task (``gold_coin``,
    ``pick_place``) and each phase's (and control's) metrics on it under that name, with the gain over the control
    on each of its scores, seed by seed, under ``unseen_gain`` (:func:`unseen_gain`); for evolution phases the
    discriminator counts, the equal-compute control's metrics and the gain of the phase over it; and the dataset's
    own score where the reference stage measured it.

    Means and standard errors are over training seeds (over episodes with one seed: ``stderr_over``), 95 % intervals
    over seeds (``*_ci_low``, ``*_ci_high``; two or more seeds) and over episodes (``*_episode_ci_low``,
    ``*_episode_ci_high``; :mod:`adaptdiffuser.seed_metrics`); the held-out start states' under ``held_out``; the
    discriminator counts are means over seeds; ``per_seed`` has each seed's score and gain."""
    summary: dict[str, dict] = {}
    for task in params.tasks:
        entry: dict[str, Any] = {}
        ref = read_json(root / reference_path(task), f"reference of {task} (run reference@{task})")
        entry["reference"] = {key: ref[key] for key in REFERENCE_KEYS if key in ref}
        if "dataset" in ref:
            entry["dataset"] = ref["dataset"]
        unseen = unseen_task_of(params.task[task]) if task in params.unseen_tasks else None
        if unseen is not None:
            entry["unseen_task"] = unseen
        for k in task_phases(params, task):
            metrics = read_json(root / phase_metrics_path(task, k), f"metrics of {task} phase {k} (run its evaluate)")
            phase = _without_seeds(metrics)
            if unseen is not None:
                unseen_phase = _unseen_file(root, task, k, unseen, control=False)
                phase[unseen] = unseen_phase[unseen]
            control = None
            if k > 0:
                report = read_json(root / discriminator_metrics_path(task, k), f"discriminator report of phase {k}")
                phase["discriminator"] = {key: report[key] for key in SUMMARY_DISCRIMINATOR_KEYS}
                phase["discriminator"]["tracked"] = report["generated"] - report["rejected_tracking"]
                control = read_json(
                    root / phase_metrics_path(task, k, control=True), f"metrics of {task} phase {k}'s control"
                )
                phase["control"] = _gain_moved(phase, _without_seeds(control))
                if unseen is not None:
                    unseen_control = _unseen_file(root, task, k, unseen, control=True)
                    phase["control"][unseen] = unseen_control[unseen]
                    phase["unseen_gain"] = unseen_gain(unseen_phase, unseen_control, unseen)
            phase["per_seed"] = _per_seed(metrics, control)
            entry[f"phase_{k}"] = phase
        summary[task] = entry
    return summary


def log_evolution(task: str, entry: dict, root: Path) -> None:
    """One MLflow run per task (``summarize``, in the pipeline's parent run) with the evolution curve as metrics at
    step k = phase: ``score`` (and ``score_stderr``), and for evolution phases ``control`` and ``gain``; the
    registered model's alias ``best`` moves to the phase with the highest score (tag ``best_phase``)."""
    phases = dict(phase_entries(entry))
    with stage_run(task, "summarize", None, {"phases": ",".join(map(str, sorted(phases)))}, root) as run:
        for k, phase in sorted(phases.items()):
            run.log_metric("score", phase["score_mean"], step=k)
            run.log_metric("score_stderr", phase["score_stderr"], step=k)
            if "control" in phase:
                run.log_metric("control", phase["control"]["score_mean"], step=k)
                run.log_metric("gain", phase["gain_mean"], step=k)
        best = max(phases, key=lambda k: phases[k]["score_mean"])
        run.set_tags({"best_phase": str(best)})
        run.set_best_alias(task, best)  # and the tag ``best_model_version``
