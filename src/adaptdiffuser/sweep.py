"""Optuna sweep over params (alpha, discriminator thresholds, ...) declared in ``params.yaml``'s ``sweep`` section.

Each trial reruns the evolution phases of the swept task (``sweep.task``, default ``evolve``: generate,
discriminate, fine-tune, evaluate, and the equal-compute control or the gold-coin evaluation when the objective
needs them) for every training seed, in its own folder ``sweeps/<study>/trial_<n>/``, reusing the project's cached
data, reference scores and phase-0 models, and reports its objective after every phase so hopeless trials are
pruned. The default objective is the final phase's gain over its control (the number the results lead with), not
its raw score. Trials evaluate on their own episodes (``sweep.evaluate_seed``), never on the pipeline's.

Workers are processes sharing one Optuna storage: a journal file by default (``sweeps/<study>.journal``), or any
RDB URL such as ``postgresql://user@host/db`` for workers on several machines (then Optuna heartbeats fail and
retry the trials of killed workers; with the journal file the sweep command does that for its own workers).

MLflow: one parent run per sweep, one child run per trial (params, per-phase scores, objective), and each
trial's stage runs nested under its child run.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import optuna
import yaml

from adaptdiffuser.config import Params, SearchDimension, SweepParams, params_from_dict, set_dotted
from adaptdiffuser.errors import StageError
from adaptdiffuser.tracking import PARENT_RUN_ENV


def shared_inputs(task: str) -> tuple[Path, ...]:
    """The cached pipeline outputs of the swept task that every trial reuses (phase 0 is never retrained)."""
    from adaptdiffuser.stages.common import collect_dir, dataset_path, phase_models_dir, reference_path

    return (dataset_path(task), collect_dir(task), phase_models_dir(task, 0), reference_path(task))


def swept_task(params: Params) -> str:
    """The task the trials evolve: ``sweep.task``, or ``evolve`` when that is null."""
    task = params.sweep.task if params.sweep.task is not None else params.evolve
    if task is None:
        raise StageError("the sweep needs a task to evolve: set sweep.task or evolve")
    return task


def objective_value(sweep: SweepParams, metrics: dict[str, dict]) -> float:
    """The sweep's score of one evaluated phase from its ``evaluate`` metrics (and ``control`` or ``gold_coin``
    where the objective needs them): ``gain`` = score - control score (paired, mean over seeds), ``score`` =
    normalized score, ``coin`` = 100 x coin both-rate, ``mix`` = (1 - coin_weight) x score + coin_weight x coin."""
    if sweep.objective == "gain":
        return float(metrics["control"]["gain_mean"])
    score = float(metrics["evaluate"]["score_mean"])
    if sweep.objective == "score":
        return score
    coin = 100.0 * float(metrics["gold_coin"]["both_rate"])
    if sweep.objective == "coin":
        return coin
    return (1.0 - sweep.coin_weight) * score + sweep.coin_weight * coin


def suggest(trial: optuna.Trial, dim: SearchDimension) -> Any:
    """Sample one search dimension."""
    if dim.kind == "categorical":
        return trial.suggest_categorical(dim.key, list(dim.choices))
    if dim.kind == "int":
        return trial.suggest_int(dim.key, int(dim.low), int(dim.high), log=dim.log)
    return trial.suggest_float(dim.key, dim.low, dim.high, log=dim.log)


def trial_params(raw: dict[str, Any], values: dict[str, Any]) -> Params:
    """The project's params with a trial's values set (and validated), evolving the swept task and evaluating on
    the sweep's own episodes (``sweep.evaluate_seed``, also where the task overrides ``evaluate``); the ``sweep``
    section itself is left out (pass ``base.sweep`` to :func:`run_trial`)."""
    base = params_from_dict(raw)
    task = swept_task(base)
    raw = {key: value for key, value in raw.items() if key != "sweep"}
    for key, value in values.items():
        raw = set_dotted(raw, key, value)
    raw = set_dotted(raw, "evolve", task)
    raw = set_dotted(raw, "evaluate.seed", base.sweep.evaluate_seed)
    if "seed" in (raw.get("task", {}).get(task, {}) or {}).get("evaluate", {}):
        raw = set_dotted(raw, f"task.{task}.evaluate.seed", base.sweep.evaluate_seed)
    return params_from_dict(raw)


def reproduce_command(values: dict[str, Any]) -> str:
    """The ``dvc exp run`` command that reruns the pipeline with a trial's values."""
    return "dvc exp run " + " ".join(f"-S '{key}={_yaml_scalar(value)}'" for key, value in values.items())


def _yaml_scalar(value: Any) -> str:
    return yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("\n...").strip()


def make_storage(spec: str | None, root: Path, study: str, heartbeat_s: int) -> optuna.storages.BaseStorage:
    """A journal file (``spec`` a path; default ``sweeps/<study>.journal``) or, for a URL such as
    ``postgresql://...``, an RDB storage with heartbeats that fail and retry (once) the trials of dead workers."""
    if spec is None or "://" not in spec:
        path = Path(spec) if spec else root / "sweeps" / f"{study}.journal"
        path.parent.mkdir(parents=True, exist_ok=True)
        from optuna.storages.journal import JournalFileBackend

        return optuna.storages.JournalStorage(JournalFileBackend(str(path)))
    retry = getattr(optuna.storages, "RetryHeartbeatStaleTrialCallback", None)
    if retry is not None:  # optuna >= 4.9
        callback = {"heartbeat_stale_trial_callback": retry(max_retry=1)}
    else:
        callback = {"failed_trial_callback": optuna.storages.RetryFailedTrialCallback(max_retry=1)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.storages.RDBStorage(
            spec, heartbeat_interval=heartbeat_s, grace_period=2 * heartbeat_s, **callback
        )


@dataclass
class TrialContext:
    """What a worker needs: the project root, its params file contents, the storage spec and MLflow ids."""

    root: Path
    raw: dict[str, Any]
    storage: str | None
    parent_run_id: str
    tracking_uri: str
    device: str
    threads: int


def check_shared_inputs(root: Path, task: str) -> None:
    """The cached pipeline outputs every trial reuses must exist (a sweep never retrains phase 0)."""
    for rel in shared_inputs(task):
        if not (root / rel).exists():
            raise FileNotFoundError(f"{rel} not found: run `dvc repro` (at least up to pretrain) before a sweep")


def _link_shared_inputs(root: Path, trial_dir: Path, task: str) -> None:
    check_shared_inputs(root, task)
    for rel in shared_inputs(task):
        source = (root / rel).resolve()
        target = trial_dir / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        if not target.exists():
            target.symlink_to(source, target_is_directory=source.is_dir())


def run_trial(
    params: Params,
    sweep: SweepParams,
    root: Path,
    trial_dir: Path,
    device: Any,
    report: Callable[[int, float, dict], None],
) -> float:
    """Run every evolution phase of ``params`` (from :func:`trial_params`) in ``trial_dir``, for every training
    seed; ``report(k, value, metrics)`` after each phase (it may raise :class:`optuna.TrialPruned`). Returns the
    final phase's objective."""
    from adaptdiffuser.stages.discriminate import run_discriminate
    from adaptdiffuser.stages.evaluate import run_evaluate
    from adaptdiffuser.stages.evaluate_coin import run_evaluate_coin
    from adaptdiffuser.stages.finetune import run_finetune
    from adaptdiffuser.stages.generate import run_generate

    if not params.phases or params.evolve is None:
        raise StageError("the sweep needs at least one evolution phase under 'phases' and a task to 'evolve'")
    task = params.evolve
    objective = sweep.objective
    _link_shared_inputs(root, trial_dir, task)
    value = math.nan
    for phase in params.phases:
        k = phase.index
        run_generate(params, task, trial_dir, k, device, progress=False)
        run_discriminate(params, task, trial_dir, k, progress=False)
        run_finetune(params, task, trial_dir, k, device, progress=False)
        metrics = {"evaluate": run_evaluate(params, task, trial_dir, k, device, progress=False)}
        if objective == "gain":
            run_finetune(params, task, trial_dir, k, device, progress=False, control=True)
            metrics["control"] = run_evaluate(params, task, trial_dir, k, device, progress=False, control=True)
        if objective in ("coin", "mix"):
            metrics["gold_coin"] = run_evaluate_coin(params, task, trial_dir, k, device, progress=False)
        value = objective_value(sweep, metrics)
        report(k, value, metrics)
    return value


def _worker(ctx: TrialContext, study_name: str, n_trials: int, worker: int) -> None:
    """One worker process: load the shared study and run ``n_trials`` trials."""
    import mlflow
    import torch
    from mlflow.tracking import MlflowClient

    from adaptdiffuser.stages.common import resolve_device
    from adaptdiffuser.tracking import ensure_experiment

    torch.set_num_threads(ctx.threads)
    os.environ["MLFLOW_TRACKING_URI"] = ctx.tracking_uri
    mlflow.set_tracking_uri(ctx.tracking_uri)
    client = MlflowClient(ctx.tracking_uri)
    base = params_from_dict(ctx.raw)
    sweep = base.sweep
    experiment_id = ensure_experiment(swept_task(base), ctx.root)
    storage = make_storage(ctx.storage, ctx.root, study_name, sweep.heartbeat_s)
    study = optuna.load_study(study_name=study_name, storage=storage, sampler=_sampler(sweep, worker))
    device = resolve_device(ctx.device)

    def objective(trial: optuna.Trial) -> float:
        trial.set_user_attr("worker_pid", os.getpid())
        values = {dim.key: suggest(trial, dim) for dim in sweep.space}
        params = trial_params(ctx.raw, values)
        run = client.create_run(
            experiment_id,
            run_name=f"{study_name}-trial{trial.number}",
            tags={"mlflow.parentRunId": ctx.parent_run_id, "sweep": study_name, "trial": str(trial.number)},
        )
        run_id = run.info.run_id
        for key, value in values.items():
            client.log_param(run_id, key, value)
        os.environ[PARENT_RUN_ENV] = run_id
        status = "FAILED"

        def report(k: int, value: float, metrics: dict) -> None:
            client.log_metric(run_id, "objective", value, step=k)
            client.log_metric(run_id, "score_mean", metrics["evaluate"]["score_mean"], step=k)
            if "control" in metrics:
                client.log_metric(run_id, "control.score_mean", metrics["control"]["score_mean"], step=k)
                client.log_metric(run_id, "gain_mean", metrics["control"]["gain_mean"], step=k)
            if "gold_coin" in metrics:
                client.log_metric(run_id, "gold_coin.both_rate", metrics["gold_coin"]["both_rate"], step=k)
            trial.report(value, k)
            if trial.should_prune():
                raise optuna.TrialPruned(f"phase {k}: objective {value:.2f} is below the running median")

        try:
            trial_dir = ctx.root / "sweeps" / study_name / f"trial_{trial.number}"
            value = run_trial(params, sweep, ctx.root, trial_dir, device, report)
            client.log_metric(run_id, "final_objective", value)
            status = "FINISHED"
            return value
        except optuna.TrialPruned:
            status = "KILLED"
            client.set_tag(run_id, "pruned", "true")
            raise
        finally:
            os.environ.pop(PARENT_RUN_ENV, None)
            client.set_terminated(run_id, status)

    study.optimize(objective, n_trials=n_trials, catch=(StageError,))


def _sampler(sweep: SweepParams, worker: int) -> optuna.samplers.BaseSampler:
    return optuna.samplers.TPESampler(seed=sweep.seed + worker, n_startup_trials=max(2, sweep.workers))


@dataclass
class SweepResult:
    study: optuna.Study
    best_values: dict[str, Any]
    best_value: float
    command: str
    parent_run_id: str


def run_sweep(
    root: Path,
    params_path: Path,
    trials: int | None = None,
    workers: int | None = None,
    storage: str | None = None,
    device: str = "auto",
) -> SweepResult:
    """Create (or resume) the study named in ``sweep.study`` and run ``trials`` trials on ``workers`` worker
    processes; log the sweep to MLflow (parent run + one child per trial) and return the best trial."""
    from mlflow.tracking import MlflowClient

    from adaptdiffuser.tracking import ensure_experiment, tracking_uri

    raw = yaml.safe_load(params_path.read_text()) or {}
    params = params_from_dict(raw)  # the search space is validated here, before any trial starts
    sweep = params.sweep
    if not sweep.space:
        raise StageError("sweep.space is empty: declare at least one params key to search")
    trials = trials or sweep.trials
    workers = workers or sweep.workers
    storage = storage or sweep.storage
    if not params.phases:
        raise StageError("the sweep reruns the evolution phases: declare 'phases'")
    task = swept_task(params)
    check_shared_inputs(root, task)
    uri = tracking_uri(root)
    client = MlflowClient(uri)
    experiment_id = ensure_experiment(task, root)
    parent = client.create_run(
        experiment_id,
        run_name=f"sweep-{sweep.study}",
        tags={"stage": "sweep", "sweep": sweep.study, "storage": storage or "journal file"},
    )
    parent_id = parent.info.run_id
    client.log_param(parent_id, "trials", trials)
    client.log_param(parent_id, "workers", workers)
    client.log_param(parent_id, "objective", sweep.objective)
    client.log_param(parent_id, "task", task)
    client.log_param(parent_id, "evaluate_seed", sweep.evaluate_seed)
    for dim in sweep.space:
        client.log_param(parent_id, f"space.{dim.key}", _describe(dim))
    study_storage = make_storage(storage, root, sweep.study, sweep.heartbeat_s)
    study = optuna.create_study(
        study_name=sweep.study,
        storage=study_storage,
        direction="maximize",
        load_if_exists=True,
        pruner=optuna.pruners.MedianPruner(n_startup_trials=sweep.pruner_startup_trials, n_warmup_steps=0),
    )
    ctx = TrialContext(
        root=root.resolve(),
        raw=raw,
        storage=storage,
        parent_run_id=parent_id,
        tracking_uri=uri,
        device=device,
        threads=max(1, (os.cpu_count() or 1) // workers),
    )
    shares = [trials // workers + (1 if i < trials % workers else 0) for i in range(workers)]
    spawn = multiprocessing.get_context("spawn")
    processes = [spawn.Process(target=_worker, args=(ctx, sweep.study, n, i)) for i, n in enumerate(shares) if n]
    for process in processes:
        process.start()
    for process in processes:
        process.join()
    _fail_trials_of_dead_workers(study, {p.pid for p in processes if p.exitcode != 0})
    completed = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if not completed:
        client.set_terminated(parent_id, "FAILED")
        raise StageError(f"study {sweep.study!r}: no trial completed (see the worker output above)")
    best = study.best_trial
    command = reproduce_command(best.params | ({"evolve": task} if task != params.evolve else {}))
    client.log_metric(parent_id, "best_objective", best.value)
    client.set_tag(parent_id, "reproduce", command)
    for key, value in best.params.items():
        client.log_param(parent_id, f"best.{key}", value)
    _log_study_plots(study, client, parent_id, root / "sweeps" / sweep.study)
    client.set_terminated(parent_id, "FINISHED")
    return SweepResult(study, dict(best.params), float(best.value), command, parent_id)


def _describe(dim: SearchDimension) -> str:
    if dim.kind == "categorical":
        return f"choices {list(dim.choices)}"
    return f"{dim.kind} [{dim.low:g}, {dim.high:g}]{' log' if dim.log else ''}"


def _fail_trials_of_dead_workers(study: optuna.Study, dead_pids: set[int]) -> None:
    """Journal storage has no heartbeat: trials left RUNNING by a worker that died are marked FAILED here, and
    their params are enqueued once to be retried by the next run of the sweep."""
    for trial in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
        if trial.user_attrs.get("worker_pid") in dead_pids:
            study._storage.set_trial_state_values(trial._trial_id, optuna.trial.TrialState.FAIL)
            if not trial.user_attrs.get("retry_of"):
                study.enqueue_trial(trial.params, user_attrs={"retry_of": trial.number})


def _log_study_plots(study: optuna.Study, client: Any, run_id: str, folder: Path) -> None:
    """Optimization history and parameter importances as PNGs on the parent run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from optuna.visualization import matplotlib as ovm

    from adaptdiffuser.io import atomic_path

    folder.mkdir(parents=True, exist_ok=True)
    plots = {"optimization_history": ovm.plot_optimization_history}
    if len([t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]) >= 2:
        plots["param_importances"] = ovm.plot_param_importances
    for name, plot in plots.items():
        try:
            ax = plot(study)
        except (ValueError, RuntimeError) as err:  # e.g. importances of a parameter that never varied
            client.set_tag(run_id, f"plot.{name}", f"not drawn: {err}")
            continue
        path = folder / f"{name}.png"
        with atomic_path(path) as tmp:
            ax.figure.savefig(tmp, format="png", dpi=100, bbox_inches="tight")
        plt.close(ax.figure)
        client.log_artifact(run_id, str(path), artifact_path="optuna")


def apply_best(params_path: Path, values: dict[str, Any]) -> None:
    """Write a trial's values into ``params.yaml``, keeping its comments and layout (ruamel round trip)."""
    from ruamel.yaml import YAML

    from adaptdiffuser.io import atomic_path

    ryaml = YAML()
    ryaml.preserve_quotes = True
    # ruamel writes None as an empty value by default; keep the file's explicit ``null``s.
    ryaml.representer.add_representer(type(None), lambda rep, _: rep.represent_scalar("tag:yaml.org,2002:null", "null"))
    data = ryaml.load(params_path.read_text())
    for key, value in values.items():
        node = data
        parts = key.split(".")
        for part in parts[:-1]:
            node = node[part]
        node[parts[-1]] = value
    with atomic_path(params_path) as tmp:
        with open(tmp, "w") as f:
            ryaml.dump(data, f)
        params_from_dict(yaml.safe_load(tmp.read_text()))
