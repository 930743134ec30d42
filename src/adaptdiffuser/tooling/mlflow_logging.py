"""MLflow tracking: one experiment per task, one run per stage execution (and training seed), tagged with stage,
phase and seed, nested under one parent run per pipeline run (:func:`pipeline_run`).

Stages do not import MLflow: they write run records (:mod:`adaptdiffuser.tooling.run_records`) and one process logs
them here (:func:`log_pending`): the summarize stage at the end of a pipeline run, a sweep worker after each trial,
``adaptdiffuser mlflow-log`` by hand. Each run keeps its stage's start and end time and status.

Each task's experiment is tagged as a model-training experiment (``mlflow.experimentKind``), so that MLflow 3's UI
opens it on its runs, not on the GenAI overview. Training stages log the datasets they train on as MLflow dataset
inputs and their EMA model, registered as a version of ``adaptdiffuser-<task>`` with the aliases ``phase<k>``
(first training seed), ``phase<k>-seed<s>``, ``phase<k>-control...``; the summarize stage adds ``best``.

The tracking URI defaults to ``sqlite:///<repo>/mlflow.db`` (``MLFLOW_TRACKING_URI`` overrides it) and each
experiment stores artifacts under an explicit absolute location, ``<repo>/mlartifacts/<task>``. A stage that
raises leaves its run marked FAILED, one stopped by SIGTERM KILLED.

A record that cannot be logged (:class:`RecordError`: unreadable, invalid, a model that no longer unpickles, content
the store refuses as invalid) is moved to ``mlflow-pending/.failed/<id>/`` with an ``error.txt``, and the others are
logged; an error of the store itself (unreachable, locked, out of space) still raises and leaves every record waiting.

Secrets never reach MLflow: every param and tag goes through :func:`redact` (the password of a URL such as
``postgresql://user:PASSWORD@host/db``, and the value of any key like ``*password*``, ``*token*``, ``*secret*`` or
``*api_key*``, become ``***``).
"""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import sys
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import mlflow
from mlflow.entities import DatasetInput, InputTag, Metric, Param
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from adaptdiffuser.tooling.run_records import (
    PARENT_RUN_ENV,
    PENDING,
    PIPELINE_KEY_TAG,
    PIPELINE_RUN_ENV,
    PIPELINE_STAGE,
    REDACTED,
    flatten,
    git_commit,
    is_secret_key,
    loggable,
    params_digest,
    pending_records,
    pending_root,
    pipeline_identity,
    pipeline_record,
    project_root,
    read_record,
    redact,
    redact_text,
    remove_dead_partials,
    stage_run,
)

__all__ = [
    "EXPERIMENT_KIND", "EXPERIMENT_KIND_TAG", "PARENT_RUN_ENV", "PENDING", "PIPELINE_KEY_TAG", "PIPELINE_RUN_ENV",
    "PIPELINE_STAGE", "RECORD_ID_TAG", "REDACTED", "Logged", "RecordError", "ensure_experiment", "flatten",
    "git_commit", "is_secret_key", "log_pending", "loggable", "params_digest", "pending_sources", "pipeline_identity",
    "pipeline_run", "project_root", "redact", "redact_text", "registered_model_name", "set_best_alias", "stage_run",
    "stage_times", "tracking_uri",
]  # fmt: skip

#: the experiment tag MLflow 3's UI reads to choose between its GenAI and its model-training views
EXPERIMENT_KIND_TAG = "mlflow.experimentKind"
EXPERIMENT_KIND = "custom_model_development"
#: the tag naming the run record a stage run was logged from (:func:`log_pending` finds a half-logged run by it)
RECORD_ID_TAG = "record_id"
#: the lock file (in the pending folder) that makes one process at a time log the pending records
LOCK_FILE = ".lock"
#: the folder (in the pending folder) of the records that could not be logged, each with an ``error.txt``
FAILED_DIR = ".failed"
#: what a record must hold, and of which type
_RECORD_KEYS = {
    "id": str, "task": str, "run_name": str, "tags": dict, "params": dict, "metrics": list, "datasets": list,
    "models": list, "start_ms": int, "end_ms": int, "status": str,
}  # fmt: skip
_STATUSES = ("FINISHED", "FAILED", "KILLED")
#: the MLflow error codes that mean the store refused the record's content (any other error is the store's)
_REFUSED = ("INVALID_PARAMETER_VALUE",)
_BATCH = 500  # metrics or params per ``log_batch`` call (MLflow takes at most 1000 metrics, 100 params)
_DATASET_CONTEXT = "mlflow.data.context"


def tracking_uri(root: Path) -> str:
    """The tracking URI in effect for a project rooted at ``root``: ``MLFLOW_TRACKING_URI`` when set, else the
    sqlite file of :func:`project_root`."""
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{(project_root(root) / 'mlflow.db').resolve()}"


def ensure_experiment(task: str, root: Path) -> str:
    """The id of the task's experiment, created if new (with an absolute artifact location under the project, or the
    tracking server's own when ``MLFLOW_TRACKING_URI`` is an ``http(s)://`` server), and tagged as a
    model-training experiment (:data:`EXPERIMENT_KIND_TAG`; an existing experiment gets the tag unless someone chose
    another kind explicitly)."""
    experiment = mlflow.get_experiment_by_name(task)
    if experiment is None:
        # a tracking server stores artifacts where it was told to (``--artifacts-destination``, served to every
        # client); the local store under the project
        remote = mlflow.get_tracking_uri().startswith(("http://", "https://"))
        location = None if remote else (project_root(root) / "mlartifacts" / task).resolve().as_uri()
        try:
            return mlflow.create_experiment(
                task, artifact_location=location, tags={EXPERIMENT_KIND_TAG: EXPERIMENT_KIND}
            )
        except MlflowException:  # created meanwhile by another process
            experiment = mlflow.get_experiment_by_name(task)
            if experiment is None:
                raise
    kind = experiment.tags.get(EXPERIMENT_KIND_TAG, "")
    if kind != EXPERIMENT_KIND and (not kind or kind.endswith("_inferred") or kind == "no_inferred_type"):
        MlflowClient().set_experiment_tag(experiment.experiment_id, EXPERIMENT_KIND_TAG, EXPERIMENT_KIND)
    return experiment.experiment_id


def pipeline_run(
    experiment_id: str, root: Path, pipeline: dict[str, Any] | None = None, start_ms: int | None = None
) -> str:
    """The id of the parent run of a pipeline run in the experiment (``pipeline``: as a record holds it, see
    :func:`~adaptdiffuser.tooling.run_records.pipeline_record`; by default this one's at ``root``): found by its
    :data:`PIPELINE_KEY_TAG`, else created (started at ``start_ms``; tags ``stage=pipeline``, the commit, the params
    digest and the DVC experiment; ``params.yaml`` as params). Should two processes create it at once, the older run
    wins and the other is deleted."""
    client = MlflowClient()
    pipeline = pipeline or pipeline_record(root)
    key, tags = pipeline["key"], dict(pipeline["tags"])
    query = f"tags.{PIPELINE_KEY_TAG} = '{key}'"

    def oldest() -> list:
        return client.search_runs([experiment_id], query, order_by=["attributes.start_time ASC"], max_results=5)

    found = oldest()
    if found:
        return found[0].info.run_id
    note = (
        "The stage runs of one pipeline run (`dvc repro` at one git commit and params.yaml, or one `dvc exp run`). "
        f"Key {key}: {', '.join(f'{k}={v}' for k, v in tags.items())}."
    )
    tags |= {"stage": PIPELINE_STAGE, PIPELINE_KEY_TAG: key, "mlflow.note.content": note}
    run = client.create_run(experiment_id, start_time=start_ms, run_name=pipeline["name"], tags=loggable(tags, 5000))
    run_id = run.info.run_id
    winner = oldest()[0].info.run_id
    if winner != run_id:
        client.delete_run(run_id)
        return winner
    items = list(pipeline["params"].items())
    for start in range(0, len(items), 100):
        client.log_batch(run_id, params=[Param(k, v) for k, v in items[start : start + 100]])
    return run_id


class RecordError(Exception):
    """A run record that cannot be logged, whatever the store: unreadable or invalid, a model that no longer
    unpickles, or content the store refuses as invalid (MLflow's ``INVALID_PARAMETER_VALUE``)."""


class Logged(dict[str, str]):
    """What :func:`log_pending` logged, ``{record id: run id}``, and in :attr:`failed` the records it could not log,
    ``{record id: error}`` (moved to ``mlflow-pending/.failed/``)."""

    def __init__(self) -> None:
        super().__init__()
        self.failed: dict[str, str] = {}


def log_pending(root: Path, store: Path | None = None) -> Logged:
    """Log every pending run record of the project at ``root`` (:func:`~adaptdiffuser.tooling.run_records.stage_run`;
    or of a sweep trial's folder) to the MLflow store of the project at ``store`` (default ``root``, see
    :func:`tracking_uri`), oldest first, as the stage would have logged it itself; ``{record id: run id}``.

    One process at a time (an exclusive lock on ``mlflow-pending/.lock``: two queue workers may finish at once). A
    record is deleted only once it is fully logged; a run that a crash left half-logged (found by its
    :data:`RECORD_ID_TAG`, its end time not yet the record's) is deleted with its model versions and logged again.
    A record that cannot be logged (:class:`RecordError`) goes to ``mlflow-pending/.failed/<id>/`` with its error in
    ``error.txt``, one warning line on stderr, and the others are logged (:attr:`Logged.failed`); any other error
    (the store's) raises. The hidden folders of stages that died without writing their record are deleted
    (:func:`~adaptdiffuser.tooling.run_records.remove_dead_partials`)."""
    root = root.resolve()
    store = (store or root).resolve()
    folder = pending_root(root)
    logged = Logged()
    remove_dead_partials(root)
    if not pending_records(root):
        return logged
    before = os.environ.get("MLFLOW_TRACKING_URI")  # set_tracking_uri sets it too: put back after, for the next store
    mlflow.set_tracking_uri(tracking_uri(store))
    with open(folder / LOCK_FILE, "a") as lock, _quiet_model_logging():
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            for record in pending_records(root):  # again under the lock: another process may have logged some
                try:
                    logged[record.name] = _log_record(record, store)
                except RecordError as err:
                    logged.failed[record.name] = str(err)
                    _quarantine(record, err)
                    continue
                done = record.with_name(f".{record.name}.done")
                os.replace(record, done)  # gone from the pending records at once, then deleted
                shutil.rmtree(done)
            for leftover in folder.glob(".*.done"):  # a deletion that a crash interrupted
                shutil.rmtree(leftover, ignore_errors=True)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
            mlflow.set_tracking_uri(before)
    return logged


def pending_sources(path: Path) -> list[tuple[Path, Path]]:
    """Where :func:`log_pending` finds records and where it logs them, ``[(root, store)]``, for ``path``: a project
    root (its own records, then those of its sweep trials, ``sweeps/*/trial_*/mlflow-pending``, logged to the
    project's store), or a ``mlflow-pending`` folder (a sweep trial's is logged to its project's store)."""
    path = path.resolve()
    if path.name == PENDING:
        root = path.parent
        trial = root.name.startswith("trial_") and root.parent.parent.name == "sweeps"
        return [(root, root.parents[2] if trial else root)]
    trials = sorted(t for t in path.glob("sweeps/*/trial_*") if (t / PENDING).is_dir())
    return [(path, path)] + [(trial, path) for trial in trials]


def _quarantine(record: Path, error: RecordError) -> None:
    """Move the record folder ``record`` to ``.failed/`` beside it, with ``error.txt``; one warning line."""
    from adaptdiffuser.io import atomic_path

    with atomic_path(record / "error.txt") as tmp:
        tmp.write_text(f"{error}\n")
    target = record.parent / FAILED_DIR / record.name
    target.parent.mkdir(exist_ok=True)
    if target.exists():  # a record of the same id failed before (moved back by hand): the newer one is kept
        shutil.rmtree(target)
    os.replace(record, target)
    print(f"warning: run record {record.name} not logged to MLflow, moved to {target}: {error}", file=sys.stderr)


def _read_valid(folder: Path) -> tuple[dict[str, Any], list[Any]]:
    """The record in ``folder`` and its models (unpickled), or :class:`RecordError` naming what is wrong. Torch is
    imported only for a record that holds models."""
    try:
        record = read_record(folder)
    except (OSError, ValueError) as err:
        raise RecordError(f"unreadable {folder.name}/record.json: {err}") from err
    if not isinstance(record, dict):
        raise RecordError("record.json is not a mapping")
    for key, kind in _RECORD_KEYS.items():
        if not isinstance(record.get(key), kind):
            raise RecordError(f"record.json: {key!r} missing or not a {kind.__name__}")
    if record["status"] not in _STATUSES:
        raise RecordError(f"record.json: status {record['status']!r} is none of {', '.join(_STATUSES)}")
    if record.get("parent_run_id") is None and not isinstance(record.get("pipeline"), dict):
        raise RecordError("record.json: neither a parent run id nor a pipeline")
    modules = []
    if record["models"]:
        import torch
    for model in record["models"]:
        try:
            modules.append(torch.load(folder / model["folder"] / "model.pt", map_location="cpu", weights_only=False))
        except Exception as err:  # noqa: BLE001 - unpickling runs arbitrary code: any error is the record's
            raise RecordError(f"model {model.get('folder')!r} cannot be loaded: {type(err).__name__}: {err}") from err
    return record, modules


def _log_record(folder: Path, root: Path) -> str:
    """Log the record in ``folder`` as one MLflow run (see :func:`log_pending`); its run id. :class:`RecordError`
    if the record cannot be logged (the run half-logged meanwhile, and its parent, end FAILED)."""
    record, modules = _read_valid(folder)
    client = MlflowClient()
    experiment_id = ensure_experiment(record["task"], root)
    run_id = parent = None
    try:
        for run in client.search_runs([experiment_id], f"tags.{RECORD_ID_TAG} = '{record['id']}'"):
            if run.info.end_time == record["end_ms"] and run.info.status == record["status"]:
                # logged whole before a crash: only the parent's end (if the crash came before it) and the
                # record's deletion were left
                if record["parent_run_id"] is None:
                    _end_parent(client, run.data.tags["mlflow.parentRunId"], record)
                return run.info.run_id
            for version in client.search_model_versions(f"run_id = '{run.info.run_id}'"):
                client.delete_model_version(version.name, version.version)
            client.delete_run(run.info.run_id)
        tags = {**record["tags"], RECORD_ID_TAG: record["id"]}
        parent = record["parent_run_id"]
        if parent is None:
            parent = pipeline_run(experiment_id, root, record["pipeline"], record["start_ms"])
            client.update_run(parent, status="RUNNING")
        tags["mlflow.parentRunId"] = parent
        run_id = client.create_run(
            experiment_id, start_time=record["start_ms"], run_name=record["run_name"], tags=tags
        ).info.run_id
        params = [Param(k, v) for k, v in record["params"].items()]
        metrics = [Metric(m["key"], m["value"], m["timestamp"], m["step"]) for m in record["metrics"]]
        for start in range(0, max(len(params), len(metrics)), _BATCH):
            client.log_batch(run_id, metrics=metrics[start : start + _BATCH], params=params[start : start + _BATCH])
        if record["datasets"]:
            client.log_inputs(run_id, datasets=[_dataset_input(d) for d in record["datasets"]])
        if (folder / "artifacts").is_dir():
            client.log_artifacts(run_id, str(folder / "artifacts"))
        for model, module in zip(record["models"], modules, strict=True):
            _log_model(folder / model["folder"], model, run_id, module)
        if record["best_alias"] is not None:
            best = record["best_alias"]
            client.set_tag(run_id, "best_model_version", str(set_best_alias(best["task"], best["phase"])))
        client.set_terminated(run_id, record["status"], end_time=record["end_ms"])
    except MlflowException as err:
        if err.error_code not in _REFUSED:
            raise  # the store's error: every record waits for the next try
        for refused in (run_id, parent if record["parent_run_id"] is None else None):
            if refused is not None:
                with suppress(MlflowException):
                    client.set_terminated(refused, "FAILED", end_time=record["end_ms"])
        raise RecordError(f"MLflow refused it: {err.message}") from err
    if record["parent_run_id"] is None:
        _end_parent(client, parent, record)
    return run_id


def _end_parent(client: MlflowClient, parent: str, record: dict[str, Any]) -> None:
    """End the pipeline's parent run with the status of its stage run logged last (``record``'s: stages are logged
    in start order) and the latest end of its stage runs."""
    ended = client.get_run(parent).info.end_time or 0
    client.set_terminated(parent, record["status"], end_time=max(ended, record["end_ms"]))


def _dataset_input(dataset: dict[str, str]) -> DatasetInput:
    """A recorded dataset as MLflow's ``MetaDataset`` input (its file as a local artifact source)."""
    from mlflow.data.dataset_source_registry import get_registered_sources
    from mlflow.data.meta_dataset import MetaDataset

    local = next(cls for cls in get_registered_sources() if cls.__name__ == "LocalArtifactDatasetSource")
    meta = MetaDataset(local(dataset["source"]), name=dataset["name"], digest=dataset["digest"])
    return DatasetInput(meta._to_mlflow_entity(), tags=[InputTag(_DATASET_CONTEXT, dataset["context"])])


def registered_model_name(task: str) -> str:
    """The MLflow registered model holding a task's trained models: ``adaptdiffuser-<task>``."""
    return f"adaptdiffuser-{task}"


def _log_model(folder: Path, model: dict[str, Any], run_id: str, module: Any) -> None:
    """Log a recorded model (``module``, unpickled from ``folder``, see :meth:`StageRecord.log_model`) to the run
    ``run_id`` with
    ``mlflow.pytorch`` (pickled; its ``config.json`` and ``normalizer.json`` beside it), so that
    ``mlflow.pytorch.load_model`` gives it back; register it as a version of :func:`registered_model_name` with
    the aliases ``<label>-seed<s>`` and, for the ``primary`` (first) training seed, ``<label>``; a sweep trial's
    model is logged, not registered."""
    from importlib.metadata import version as package_version

    import mlflow.pytorch

    mlflow.start_run(run_id=run_id)  # ``mlflow.pytorch.log_model`` logs to the active run
    try:
        info = mlflow.pytorch.log_model(
            module,
            name="model",
            serialization_format="pickle",
            pip_requirements=[f"torch=={package_version('torch')}"],  # no inference (it imports the model again)
            extra_files=[str(folder / name) for name in model["extra_files"]],
        )
    finally:
        mlflow.end_run(status="RUNNING")  # the record's own status and end time are set last
    if model["register"]:
        _register(info, run_id, model)


@contextmanager
def _quiet_model_logging() -> Iterator[None]:
    """No warning from ``mlflow.pytorch`` (that pickles execute code when loaded, at every call) and no progress bar
    for the files MLflow copies while logging and registering a model."""
    quiet = logging.getLogger("mlflow.pytorch")
    level, bar = quiet.level, os.environ.get("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR")
    quiet.setLevel(logging.ERROR)
    os.environ["MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR"] = "false"
    try:
        yield
    finally:
        quiet.setLevel(level)
        if bar is None:
            os.environ.pop("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", None)
        else:
            os.environ["MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR"] = bar


def _register(info: Any, run_id: str, model: dict[str, Any]) -> str:
    """Register the logged model ``info`` (of the run ``run_id``) as a new version of the task's model, with its
    aliases."""
    client = MlflowClient()
    name = registered_model_name(model["task"])
    try:
        client.get_registered_model(name)
    except MlflowException:
        with suppress(MlflowException):  # created meanwhile
            client.create_registered_model(name, description=f"AdaptDiffuser's EMA diffusion models of {model['task']}")
    created = client.create_model_version(
        name, info.model_uri, run_id=run_id, tags=model["tags"], model_id=info.model_id
    )
    client.set_registered_model_alias(name, f"{model['label']}-seed{model['seed']}", created.version)
    if model["primary"]:
        client.set_registered_model_alias(name, model["label"], created.version)
    return created.version


def set_best_alias(task: str, phase: int) -> str | None:
    """Point the alias ``best`` of the task's registered model at the version aliased ``phase<k>``; the version, or
    None when there is none (models trained before registration existed, or only inside sweeps)."""
    client = MlflowClient()
    name = registered_model_name(task)
    try:
        version = client.get_model_version_by_alias(name, f"phase{phase}").version
    except MlflowException:
        return None
    client.set_registered_model_alias(name, "best", version)
    return version


def stage_times(root: Path) -> list[dict[str, Any]]:
    """How long each stage run of this pipeline run took (:func:`pipeline_identity` at ``root``: this commit and
    params.yaml), over every task's experiment, in the order they started: task, run name, status, seconds. Pending
    run records are logged first."""
    root = root.resolve()
    log_pending(root)
    mlflow.set_tracking_uri(tracking_uri(root))
    client = MlflowClient()
    key = pipeline_identity(root)[0]
    rows = []
    for experiment in client.search_experiments():
        parents = client.search_runs([experiment.experiment_id], f"tags.{PIPELINE_KEY_TAG} = '{key}'")
        for parent in parents:
            query = f"tags.mlflow.parentRunId = '{parent.info.run_id}'"
            for run in client.search_runs([experiment.experiment_id], query, max_results=10_000):
                end = run.info.end_time or run.info.start_time
                seconds = (end - run.info.start_time) / 1000
                rows.append({"task": experiment.name, "run": run.info.run_name, "status": run.info.status,
                             "start": run.info.start_time, "seconds": seconds})  # fmt: skip
    return sorted(rows, key=lambda row: row["start"])
