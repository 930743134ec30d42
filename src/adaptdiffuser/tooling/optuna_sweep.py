"""Optuna sweep over params (alpha, discriminator thresholds, ...) declared in ``params.yaml``'s ``sweep`` section.

Each trial reruns the evolution phases of the swept task (``sweep.task``, default ``evolve``: generate,
discriminate, fine-tune, evaluate, and the equal-compute control or the unseen-task evaluation when the objective
needs them) for every training seed, in its own folder ``sweeps/<study>/trial_<n>/``, with the stage commands of
``dvc.yaml`` (see :mod:`adaptdiffuser.tooling.sweep_trials`), reusing the project's cached data, reference scores and
phase-0 models (a search key that would change those is refused), and reports its objective after every phase so
hopeless trials are pruned. The default objective is the final phase's gain over its control (the number the
results lead with), not its raw score. Trials evaluate on start states of their own (``sweep.evaluate_seed``, and
``sweep.held_out_seed`` for the held-out set), never on the pipeline's evaluation or held-out ones.

Workers are processes sharing one Optuna storage: a journal file by default (``sweeps/<study>.journal``), or any
RDB URL such as ``postgresql://user@host/db`` for workers on several machines (its password from ``PGPASSWORD``
or ``~/.pgpass``, never logged: see :func:`~adaptdiffuser.tooling.mlflow_logging.redact`). The sweep fails and retries
(once) the trial of any of its workers that dies, on both storages, and hands the rest of its share to a new
worker (:func:`run_workers`); on PostgreSQL, Optuna heartbeats do the same for workers on other machines.

MLflow: one parent run per sweep, one child run per trial (params, per-phase scores, objective), and each
trial's stage runs nested under its child run.
"""

from __future__ import annotations

import copy
import multiprocessing
import os
import sys
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import wait
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

import optuna
import yaml

from adaptdiffuser.config import SearchDimension, SweepParams, params_from_dict
from adaptdiffuser.errors import StageError
from adaptdiffuser.tooling.dvc_experiments import (
    ExperimentMode,
    check_experiment_repo,
    record_experiment,
    set_param_args,
)
from adaptdiffuser.tooling.mlflow_logging import PARENT_RUN_ENV, loggable, redact_text
from adaptdiffuser.tooling.sweep_trials import check_sweep_plan, run_trial, swept_task, trial_raw


def suggest(trial: optuna.Trial, dim: SearchDimension) -> Any:
    """Sample one search dimension."""
    if dim.kind == "categorical":
        return trial.suggest_categorical(dim.key, list(dim.choices))
    if dim.kind == "int":
        return trial.suggest_int(dim.key, int(dim.low), int(dim.high), log=dim.log)
    return trial.suggest_float(dim.key, dim.low, dim.high, log=dim.log)


def reproduce_command(values: dict[str, Any]) -> str:
    """The ``dvc exp run`` command that reruns the pipeline with a trial's values."""
    args = set_param_args(values)
    return "dvc exp run " + " ".join(f"-S '{assignment}'" for assignment in args[1::2])


def make_storage(spec: str | None, root: Path, study: str, heartbeat_s: int) -> optuna.storages.BaseStorage:
    """A journal file (``spec`` a path; default ``sweeps/<study>.journal``) or, for a URL such as
    ``postgresql://...``, an RDB storage with heartbeats that fail and retry (once, :func:`retry_callback`) the
    trials of dead workers anywhere. An error opening it never shows the URL's password."""
    if spec is None or "://" not in spec:
        path = Path(spec) if spec else root / "sweeps" / f"{study}.journal"
        path.parent.mkdir(parents=True, exist_ok=True)
        from optuna.storages.journal import JournalFileBackend

        return optuna.storages.JournalStorage(JournalFileBackend(str(path)))
    new_name = hasattr(optuna.storages, "RetryHeartbeatStaleTrialCallback")  # optuna >= 4.9
    callback = {"heartbeat_stale_trial_callback" if new_name else "failed_trial_callback": retry_callback()}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        try:
            return optuna.storages.RDBStorage(
                spec, heartbeat_interval=heartbeat_s, grace_period=2 * heartbeat_s, **callback
            )
        except Exception as err:  # one redacted line, and no chained traceback that could show the URL
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            raise StageError(f"cannot open the Optuna storage {redact_text(spec)}: {redact_text(first)}") from None


def retry_callback() -> Callable[[optuna.Study, optuna.trial.FrozenTrial], None]:
    """Optuna's retry callback, one retry per trial: it adds a WAITING copy of a failed trial with the same params,
    marked as a retry (``RetryHeartbeatStaleTrialCallback.retried_trial_number``: the original trial's number)."""
    retry = getattr(optuna.storages, "RetryHeartbeatStaleTrialCallback", None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        warnings.simplefilter("ignore", FutureWarning)
        return (retry or optuna.storages.RetryFailedTrialCallback)(max_retry=1)


def retried_trial_number(trial: optuna.trial.FrozenTrial) -> int | None:
    """The number of the trial that ``trial`` retries (the last one if it retries a retry), or None."""
    history = trial.system_attrs.get("retry_history") or []
    return int(history[-1]) if history else None


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


def _worker(ctx: TrialContext, study_name: str, n_trials: int, worker: int) -> None:
    """One worker process: load the shared study and run ``n_trials`` trials."""
    import mlflow
    import torch
    from mlflow.tracking import MlflowClient

    from adaptdiffuser.tooling.mlflow_logging import ensure_experiment

    torch.set_num_threads(ctx.threads)
    os.environ["MLFLOW_TRACKING_URI"] = ctx.tracking_uri
    mlflow.set_tracking_uri(ctx.tracking_uri)
    client = MlflowClient(ctx.tracking_uri)
    base = params_from_dict(ctx.raw)
    sweep = base.sweep
    experiment_id = ensure_experiment(swept_task(base), ctx.root)
    study = load_worker_study(ctx.storage, ctx.root, study_name, sweep, worker)

    def objective(trial: optuna.Trial) -> float:
        trial.set_user_attr("worker_pid", os.getpid())
        values = {dim.key: suggest(trial, dim) for dim in sweep.space}
        raw = trial_raw(ctx.raw, values)
        run = client.create_run(
            experiment_id,
            run_name=f"{study_name}-trial{trial.number}",
            tags={"mlflow.parentRunId": ctx.parent_run_id, "sweep": study_name, "trial": str(trial.number)},
        )
        run_id = run.info.run_id
        for key, value in loggable(values).items():
            client.log_param(run_id, key, value)
        os.environ[PARENT_RUN_ENV] = run_id
        status = "FAILED"

        def report(k: int, value: float, metrics: dict) -> None:
            client.log_metric(run_id, "objective", value, step=k)
            client.log_metric(run_id, "score_mean", metrics["evaluate"]["score_mean"], step=k)
            if "control" in metrics:
                client.log_metric(run_id, "control.score_mean", metrics["control"]["score_mean"], step=k)
                client.log_metric(run_id, "gain_mean", metrics["control"]["gain_mean"], step=k)
            if "unseen" in metrics and "skipped" not in metrics["unseen"]:
                unseen = {k: v for k, v in metrics["unseen"].items() if k not in ("n_seeds", "seeds", "stderr_over")}
                for name, figures in unseen.items():  # {<unseen task>: {metric: value}}
                    for key, value in figures.items():
                        client.log_metric(run_id, f"{name}.{key}", value, step=k)
            trial.report(value, k)
            if trial.should_prune():
                raise optuna.TrialPruned(f"phase {k}: objective {value:.2f} is below the running median")

        trial_dir = ctx.root / "sweeps" / study_name / f"trial_{trial.number}"
        try:
            value = run_trial(raw, sweep, ctx.root, trial_dir, ctx.device, report, threads=ctx.threads)
            client.log_metric(run_id, "final_objective", value)
            status = "FINISHED"
            return value
        except optuna.TrialPruned:
            status = "KILLED"
            client.set_tag(run_id, "pruned", "true")
            raise
        finally:
            os.environ.pop(PARENT_RUN_ENV, None)
            end_trial_run(client, run_id, status, trial_dir, ctx.root)

    study.optimize(objective, n_trials=n_trials, catch=(StageError,))


def end_trial_run(client: Any, run_id: str, status: str, trial_dir: Path, root: Path) -> None:
    """After a trial: log the run records of its stages (nested under the trial's run ``run_id``) to the project's
    store, then end that run with ``status``. A logging error is one warning line, never the trial's outcome (its
    value, or its pruning, stands; the records wait for ``adaptdiffuser mlflow-log``); the run is ended anyway."""
    from adaptdiffuser.tooling.mlflow_logging import log_pending
    from adaptdiffuser.tooling.run_records import redact_text

    try:
        log_pending(trial_dir, root)
    except Exception as err:  # noqa: BLE001 - whatever MLflow raises, the trial's own outcome stands
        message = redact_text(f"{type(err).__name__}: {err}".splitlines()[0])
        print(f"warning: {trial_dir}: run records not logged to MLflow ({message})", file=sys.stderr)
    finally:
        client.set_terminated(run_id, status)


def load_worker_study(
    storage: str | None, root: Path, study_name: str, sweep: SweepParams, worker: int
) -> optuna.Study:
    """The shared study as worker number ``worker`` opens it: its own storage connection (with the heartbeat and
    retry settings of :func:`make_storage`) and a sampler seeded per worker."""
    study_storage = make_storage(storage, root, study_name, sweep.heartbeat_s)
    return optuna.load_study(
        study_name=study_name, storage=study_storage, sampler=_sampler(sweep, worker), pruner=_pruner(sweep)
    )


def _pruner(sweep: SweepParams) -> optuna.pruners.BasePruner:
    """Median pruning after ``sweep.pruner_startup_trials`` finished trials, from the first phase on."""
    return optuna.pruners.MedianPruner(n_startup_trials=sweep.pruner_startup_trials, n_warmup_steps=0)


def _sampler(sweep: SweepParams, worker: int) -> optuna.samplers.BaseSampler:
    return optuna.samplers.TPESampler(seed=sweep.seed + worker, n_startup_trials=max(2, sweep.workers))


@dataclass
class SweepResult:
    study: optuna.Study
    best_values: dict[str, Any]
    best_value: float
    command: str
    parent_run_id: str
    dvc_experiment: str | None = None  # the DVC experiment recording the best trial, when asked for


def run_sweep(
    root: Path,
    params_path: Path,
    trials: int | None = None,
    workers: int | None = None,
    storage: str | None = None,
    device: str = "auto",
    dvc_exp: ExperimentMode = "none",
) -> SweepResult:
    """Create (or resume) the study named in ``sweep.study`` and run ``trials`` trials on ``workers`` worker
    processes; log the sweep to MLflow (parent run + one child per trial) and return the best trial.

    ``dvc_exp`` ``run`` or ``queue`` also records the best trial's values as the DVC experiment
    ``<study>-best-trial<n>`` (see :mod:`adaptdiffuser.tooling.dvc_experiments`): reproduced with the pipeline's own
    evaluation episodes, which no trial saw, so its score is the sweep's held-out result."""
    from mlflow.tracking import MlflowClient

    from adaptdiffuser.tooling.mlflow_logging import ensure_experiment, tracking_uri

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
    check_sweep_plan(root, raw)  # refuses keys that change a reused stage, and missing inputs, before any trial
    if dvc_exp != "none":
        check_experiment_repo(root)
    uri = tracking_uri(root)
    client = MlflowClient(uri)
    experiment_id = ensure_experiment(task, root)
    parent_id = start_parent_run(client, experiment_id, sweep, task, storage, trials, workers)
    study_storage = make_storage(storage, root, sweep.study, sweep.heartbeat_s)
    study = optuna.create_study(
        study_name=sweep.study,
        storage=study_storage,
        direction="maximize",
        load_if_exists=True,
        pruner=_pruner(sweep),
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
    dead = run_workers(study, lambda i, n: spawn.Process(target=_worker, args=(ctx, sweep.study, n, i)), shares)
    if dead:
        client.set_tag(parent_id, "dead_workers", str(len(dead)))
    completed = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if not completed:
        client.set_terminated(parent_id, "FAILED")
        raise StageError(f"study {sweep.study!r}: no trial completed (see the worker output above)")
    best = study.best_trial
    command = reproduce_command(best.params | ({"evolve": task} if task != params.evolve else {}))
    client.log_metric(parent_id, "best_objective", best.value)
    client.set_tag(parent_id, "reproduce", redact_text(command))
    for key, value in loggable({f"best.{key}": value for key, value in best.params.items()}).items():
        client.log_param(parent_id, key, value)
    _log_study_plots(study, client, parent_id, root / "sweeps" / sweep.study)
    experiment = None
    if dvc_exp != "none":
        experiment = f"{sweep.study}-best-trial{best.number}"
        values = best.params | ({"evolve": task} if task != params.evolve else {})
        note = f"sweep {sweep.study}: trial {best.number}, objective {best.value:.4g} on the sweep's own episodes"
        try:
            record_experiment(root, experiment, values, dvc_exp, note)
        except StageError:
            client.set_terminated(parent_id, "FAILED")
            raise
        client.set_tag(parent_id, "dvc_experiment", experiment)
    client.set_terminated(parent_id, "FINISHED")
    return SweepResult(study, dict(best.params), float(best.value), command, parent_id, experiment)


def start_parent_run(
    client: Any,
    experiment_id: str,
    sweep: SweepParams,
    task: str,
    storage: str | None,
    trials: int,
    workers: int,
) -> str:
    """The sweep's parent MLflow run (tags and params redacted: a storage URL keeps its user and host, never its
    password); returns its id."""
    tags = {"stage": "sweep", "sweep": sweep.study, "storage": storage or "journal file"}
    run = client.create_run(experiment_id, run_name=f"sweep-{sweep.study}", tags=loggable(tags, 5000))
    params = {"trials": trials, "workers": workers, "objective": sweep.objective, "task": task}
    params |= {"evaluate_seed": sweep.evaluate_seed, "held_out_seed": sweep.held_out_seed}
    params |= {f"space.{dim.key}": _describe(dim) for dim in sweep.space}
    for key, value in loggable(params).items():
        client.log_param(run.info.run_id, key, value)
    return run.info.run_id


def _describe(dim: SearchDimension) -> str:
    if dim.kind == "categorical":
        return f"choices {list(dim.choices)}"
    return f"{dim.kind} [{dim.low:g}, {dim.high:g}]{' log' if dim.log else ''}"


def _fail_trials_of_dead_workers(study: optuna.Study, dead_pids: set[int]) -> list[int]:
    """Fail the trials left RUNNING by workers that died (their ``worker_pid`` user attribute) and retry each once,
    with public API only, the same way for both storages: ``study.tell(number, state=FAIL)`` and Optuna's own
    retry callback (:func:`retry_callback`), the one RDB heartbeats use. (Optuna's journal storage has no
    heartbeat, so ``optuna.storages.fail_stale_trials`` cannot see its stale trials.) A trial that something else
    finished meanwhile (an RDB heartbeat check in another worker, which retries it itself) is left alone. Returns
    the numbers of the trials failed here."""
    failed: list[int] = []
    for trial in study.get_trials(deepcopy=True, states=(optuna.trial.TrialState.RUNNING,)):
        if trial.user_attrs.get("worker_pid") not in dead_pids:
            continue
        try:
            study.tell(trial.number, state=optuna.trial.TrialState.FAIL)
        except (ValueError, optuna.exceptions.UpdateFinishedTrialError):
            continue  # finished (and, if stale, retried) by someone else since the list was read
        retry = copy.deepcopy(trial)
        retry.user_attrs = {k: v for k, v in trial.user_attrs.items() if k != "worker_pid"}  # set by the next one
        retry_callback()(study, retry)
        failed.append(trial.number)
    return failed


def run_workers(
    study: optuna.Study, make_worker: Callable[[int, int], BaseProcess], shares: Sequence[int]
) -> list[int]:
    """Run one worker process per share (``make_worker(index, n_trials)`` builds it, unstarted) until all exit.

    When one dies (nonzero exit code: killed, out of memory, crashed), its running trials are failed and retried
    once (:func:`_fail_trials_of_dead_workers`) and a new worker, with a new index (so a new sampler seed), runs the
    rest of its share plus those retries, so the study ends with the requested number of finished trials besides
    the failed ones. At most ``len(shares)`` workers are replaced, so a worker that always crashes cannot loop.
    Returns the pids of the workers that died."""
    running: dict[Any, tuple[BaseProcess, int]] = {}

    def start(index: int, n: int) -> None:
        process = make_worker(index, n)
        process.start()
        running[process.sentinel] = (process, n)

    for index, n in enumerate(shares):
        if n:
            start(index, n)
    dead: list[int] = []
    next_index = len(shares)
    while running:
        for sentinel in wait(list(running)):
            process, n = running.pop(sentinel)
            process.join()
            if process.exitcode == 0:
                continue
            assert process.pid is not None
            dead.append(process.pid)
            failed = _fail_trials_of_dead_workers(study, {process.pid})
            trials = study.get_trials(deepcopy=False)
            done = {t.number for t in trials if t.user_attrs.get("worker_pid") == process.pid and t.state.is_finished()}
            retries = sum(1 for t in trials if retried_trial_number(t) in done)
            left = n - len(done) + retries
            message = f"worker {process.pid} died (exit code {process.exitcode}); failed and retried trials {failed}"
            if left > 0 and next_index < 2 * len(shares):
                start(next_index, left)
                message += f"; worker {next_index} runs its {left} remaining trial(s)"
                next_index += 1
            print(message, file=sys.stderr, flush=True)
    return dead


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
