"""One sweep trial: the evolution stages of ``dvc.yaml`` run in the trial's own folder with the trial's params.

A trial runs the stages of each phase that its objective needs (``evaluate@phase<k>``, plus ``evaluate-control``
for ``gain`` or ``evaluate-unseen`` for ``unseen``/``mix``, and everything they depend on within the phase chain), with
the exact commands DVC would run, and reads the objective from the metrics files those stages declare. Every other
stage they depend on (collect, reference, pretrain) is reused from the project's last ``dvc repro``: a search key
that would change one of those is refused before any trial starts, naming the key and the stage.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from adaptdiffuser.config import Params, SweepParams, params_from_dict, set_dotted
from adaptdiffuser.errors import StageError
from adaptdiffuser.tooling.dvc_stages import DvcStage, key_touches, resolve_stages, upstream
from adaptdiffuser.tooling.processes import die_with_parent

# The stages (by their dvc.yaml name) whose metrics an objective reads, and the key each one's metrics go under.
OBJECTIVE_STAGES: dict[str, tuple[str, ...]] = {
    "score": ("evaluate",),
    "gain": ("evaluate", "evaluate-control"),
    "unseen": ("evaluate", "evaluate-unseen"),
    "mix": ("evaluate", "evaluate-unseen"),
}
METRICS_KEY = {"evaluate": "evaluate", "evaluate-control": "control", "evaluate-unseen": "unseen"}


def swept_task(params: Params) -> str:
    """The task the trials evolve: ``sweep.task``, or ``evolve`` when that is null."""
    task = params.sweep.task if params.sweep.task is not None else params.evolve
    if task is None:
        raise StageError("the sweep needs a task to evolve: set sweep.task or evolve")
    return task


def objective_value(
    sweep: SweepParams, metrics: dict[str, dict], unseen_objective: Callable[[dict], float] | None = None
) -> float:
    """The sweep's score of one evaluated phase from its metrics files (``evaluate``, and ``control`` or ``unseen``
    where the objective needs them): ``gain`` = score - control score (paired, mean over seeds), ``score`` =
    normalized score, ``unseen`` = ``unseen_objective`` of the unseen-task metrics (the family's figure, 0-100: the
    Maze2D gold coin's 100 x both-rate, KUKA's pick-and-place score), ``mix`` = (1 - unseen_weight) x score +
    unseen_weight x that."""
    if sweep.objective == "gain":
        return float(metrics["control"]["gain_mean"])
    score = float(metrics["evaluate"]["score_mean"])
    if sweep.objective == "score":
        return score
    if unseen_objective is None:
        raise StageError(f"sweep.objective {sweep.objective!r}: the swept task has no unseen task")
    unseen = unseen_objective(metrics["unseen"])
    if sweep.objective == "unseen":
        return unseen
    return (1.0 - sweep.unseen_weight) * score + sweep.unseen_weight * unseen


def family_unseen_objective(params: Params) -> Callable[[dict], float] | None:
    """The swept task's figure of its unseen-task metrics file (``{<unseen task>: metrics, ...}``), or None when its
    family has no unseen task."""
    from adaptdiffuser.family_registry import get_family

    family = get_family(params.task[swept_task(params)].family)
    if family.unseen_task is None:
        return None
    return lambda metrics: family.unseen_objective(metrics[family.unseen_task])


def trial_raw(raw: dict[str, Any], values: dict[str, Any]) -> dict[str, Any]:
    """The project's params (as loaded from ``params.yaml``) with a trial's values set, evolving the swept task and
    evaluating on the sweep's own start states, both sets (``sweep.evaluate_seed`` for ``evaluate.seed`` and
    ``sweep.held_out_seed`` for ``evaluate.held_out_seed``, also where the task overrides them), never the
    pipeline's; the ``sweep`` section itself is left out. Validated; returned as a plain mapping for the trial's
    params.yaml."""
    base = params_from_dict(raw)
    task = swept_task(base)
    out = {key: value for key, value in raw.items() if key != "sweep"}
    for key, value in values.items():
        out = set_dotted(out, key, value)
    out = set_dotted(out, "evolve", task)
    own = {"seed": base.sweep.evaluate_seed, "held_out_seed": base.sweep.held_out_seed}
    for key, seed in own.items():
        out = set_dotted(out, f"evaluate.{key}", seed)
        if key in ((out.get("task", {}).get(task, {}) or {}).get("evaluate", {}) or {}):
            out = set_dotted(out, f"task.{task}.evaluate.{key}", seed)
    params_from_dict(out)
    return out


@dataclass(frozen=True)
class PhaseStages:
    """What a trial runs for phase k: the stages in order, and the metrics file of each objective stage."""

    index: int
    stages: tuple[DvcStage, ...]
    metrics: dict[str, str]


@dataclass(frozen=True)
class TrialPlan:
    """The stages a trial runs per phase, the stages it reuses from the project, and the project files it reads."""

    phases: tuple[PhaseStages, ...]
    reused: tuple[DvcStage, ...]
    inputs: tuple[str, ...]


def plan_trial(root: Path, raw: dict[str, Any], objective: str) -> TrialPlan:
    """Resolve ``root/dvc.yaml`` with a trial's params (from :func:`trial_raw`) into the trial's stages."""
    params = params_from_dict(raw)
    if not params.phases or params.evolve is None:
        raise StageError("the sweep needs at least one evolution phase under 'phases' and a task to 'evolve'")
    stages = resolve_stages(root / "dvc.yaml", raw)
    index = {phase.name: phase.index for phase in params.phases}
    wanted = OBJECTIVE_STAGES[objective]
    targets = [stage for stage in stages if stage.key in index and stage.kind in wanted]
    for phase in params.phases:
        missing = set(wanted) - {stage.kind for stage in targets if stage.key == phase.name}
        if missing:
            raise StageError(
                f"dvc.yaml has no stage {sorted(missing)[0]}@{phase.name}: the '{objective}' objective reads it"
            )
    needed = upstream(stages, targets)
    run = [stage for stage in needed if stage.key in index]
    reused = tuple(stage for stage in needed if stage.key not in index)
    phases = tuple(
        PhaseStages(
            index=k,
            stages=tuple(stage for stage in run if stage.key == name),
            metrics={METRICS_KEY[s.kind]: _metrics_file(s) for s in targets if s.key == name},
        )
        for name, k in sorted(index.items(), key=lambda item: item[1])
    )
    inputs = sorted(
        {
            dep
            for stage in run
            for dep in stage.deps
            if dep != "params.yaml" and not any(other.produces(dep) for other in run)
        }
    )
    return TrialPlan(phases, reused, tuple(inputs))


def _metrics_file(stage: DvcStage) -> str:
    files = [out for out in stage.outs if out.endswith(".json")]
    if len(files) != 1:
        raise StageError(f"dvc.yaml: stage {stage.name} must declare exactly one .json metrics file, got {files}")
    return files[0]


def check_sweep_plan(root: Path, raw: dict[str, Any]) -> TrialPlan:
    """Before any trial: no search key may change a stage the trials reuse, and what they reuse must exist."""
    base = params_from_dict(raw)
    plan = plan_trial(root, trial_raw(raw, {}), base.sweep.objective)
    for dim in base.sweep.space:
        for stage in plan.reused:
            for entry in stage.params:
                if key_touches(dim.key, entry):
                    raise StageError(
                        f"sweep.space.{dim.key}: changes stage {stage.name} (it depends on params '{entry}'), which "
                        "every trial reuses from the last dvc repro; sweep a key of the evolution phases, or run "
                        f"`dvc exp run -S {dim.key}=...` to retrain"
                    )
    for path in plan.inputs:
        if not (root / path).exists() and any(stage.produces(path) for stage in plan.reused):
            raise FileNotFoundError(f"{path} not found: run `dvc repro` (at least up to pretrain) before a sweep")
    return plan


def run_trial(
    raw: dict[str, Any],
    sweep: SweepParams,
    root: Path,
    trial_dir: Path,
    device: str,
    report: Callable[[int, float, dict], None],
    threads: int | None = None,
) -> float:
    """Run a trial's stages (params ``raw`` from :func:`trial_raw`) in ``trial_dir`` phase by phase, every training
    seed inside each stage as in the pipeline; ``report(k, value, metrics)`` after each phase (it may raise
    :class:`optuna.TrialPruned`). Returns the final phase's objective."""
    from adaptdiffuser.io import atomic_path, read_json
    from adaptdiffuser.tooling.mlflow_logging import tracking_uri

    plan = plan_trial(root, raw, sweep.objective)
    unseen_objective = family_unseen_objective(params_from_dict(raw))
    trial_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(trial_dir / "params.yaml") as tmp:
        tmp.write_text(yaml.safe_dump(raw, sort_keys=False))
    _link_inputs(root, trial_dir, plan)
    env = dict(os.environ, ADAPTDIFFUSER_DEVICE=device, MLFLOW_TRACKING_URI=tracking_uri(root))
    if threads is not None:
        env["OMP_NUM_THREADS"] = str(threads)
    value = float("nan")
    for phase in plan.phases:
        for stage in phase.stages:
            run_stage_command(stage, trial_dir, env)
        metrics = {key: read_json(trial_dir / path, f"{key} metrics") for key, path in phase.metrics.items()}
        value = objective_value(sweep, metrics, unseen_objective)
        report(phase.index, value, metrics)
    return value


def _link_inputs(root: Path, trial_dir: Path, plan: TrialPlan) -> None:
    """Symlink into ``trial_dir`` every project file the trial's stages read but do not make."""
    for rel in plan.inputs:
        source, target = (root / rel).resolve(), trial_dir / rel
        if not source.exists():
            if any(stage.produces(rel) for stage in plan.reused):
                raise FileNotFoundError(f"{rel} not found: run `dvc repro` (at least up to pretrain) before a sweep")
            continue  # a code dep of a project without that file: the stage reports it if it needs it
        if not target.exists():
            target.parent.mkdir(parents=True, exist_ok=True)
            target.symlink_to(source, target_is_directory=source.is_dir())


def run_stage_command(stage: DvcStage, cwd: Path, env: dict[str, str]) -> None:
    """Run a stage's ``cmd`` as DVC would (in ``cwd``; ``python`` is this interpreter), output in ``logs/``."""
    argv = shlex.split(stage.cmd)
    if argv and argv[0] in ("python", "python3"):
        argv[0] = sys.executable
    log = cwd / "logs" / f"{stage.name.replace('@', '-')}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as out:
        code = subprocess.run(
            argv, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT, preexec_fn=die_with_parent
        ).returncode
    if code != 0:
        tail = "\n".join(log.read_text(errors="replace").splitlines()[-15:])
        raise StageError(f"trial stage {stage.name} failed with exit code {code} (log: {log}):\n{tail}")
