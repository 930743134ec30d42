"""MLflow tracking: one experiment per task, one run per stage execution (and training seed), tagged with stage,
phase and seed, nested under one parent run per pipeline run (:func:`pipeline_run`).

Each task's experiment is tagged as a model-training experiment (``mlflow.experimentKind``), so that MLflow 3's UI
opens it on its runs, not on the GenAI overview. Training stages log the datasets they train on as MLflow dataset
inputs (:func:`log_dataset`) and their EMA model (:func:`log_model`), registered as a version of
``adaptdiffuser-<task>`` with the aliases ``phase<k>`` (first training seed), ``phase<k>-seed<s>``,
``phase<k>-control...``; the summarize stage adds ``best``.

The tracking URI defaults to ``sqlite:///<repo>/mlflow.db`` (``MLFLOW_TRACKING_URI`` overrides it) and each
experiment stores artifacts under an explicit absolute location, ``<repo>/mlartifacts/<task>``. A stage that
raises leaves its run marked FAILED.

Secrets never reach MLflow: every param and tag goes through :func:`redact` (the password of a URL such as
``postgresql://user:PASSWORD@host/db``, and the value of any key like ``*password*``, ``*token*``, ``*secret*`` or
``*api_key*``, become ``***``).
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import subprocess
from collections.abc import Iterator, Mapping
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import mlflow
import yaml
from mlflow.entities import Param
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

#: set by a sweep worker to the MLflow run id of the current trial
PARENT_RUN_ENV = "ADAPTDIFFUSER_PARENT_RUN_ID"
#: names the pipeline run (parent run) the stages nest under, overriding the rule of :func:`pipeline_identity`
PIPELINE_RUN_ENV = "ADAPTDIFFUSER_PIPELINE_RUN"
#: the experiment tag MLflow 3's UI reads to choose between its GenAI and its model-training views
EXPERIMENT_KIND_TAG = "mlflow.experimentKind"
EXPERIMENT_KIND = "custom_model_development"
#: the tag that finds a pipeline run's parent run again from the next stage's process
PIPELINE_KEY_TAG = "pipeline_key"
#: the ``stage`` tag of a pipeline's parent run
PIPELINE_STAGE = "pipeline"

#: what a secret is replaced with
REDACTED = "***"
_SECRET_WORDS = r"(?:password|passwd|token|secret|api[_-]?key)"
#: a key whose value is a secret (any case, anywhere in the key: ``db_password``, ``sweep.API_KEY``)
_SECRET_KEY = re.compile(_SECRET_WORDS, re.IGNORECASE)
#: ``scheme://user:PASSWORD@``: masked up to the last ``@`` of the URL, so that an unescaped ``@`` or ``/`` in the
#: password is masked too, whichever ``@`` a parser (SQLAlchemy: the first, urllib and libpq: the last of the
#: authority) takes as its end
_URL_PASSWORD = re.compile(r"(?P<head>\b[A-Za-z][A-Za-z0-9+.\-]*://[^\s:/?#@'\"]*:)[^\s'\"<>]*@")
#: ``password=...``, ``token: ...``, ``"api_key": "..."`` inside text (query strings, libpq DSNs, YAML, JSON)
_SECRET_PAIR = re.compile(
    rf"(?P<head>[\w.\-]*{_SECRET_WORDS}[\w.\-]*['\"]?\s*[=:]\s*['\"]?)[^\s&;,'\"]+", re.IGNORECASE
)


def is_secret_key(key: str) -> bool:
    """Whether a param or tag named ``key`` holds a secret (``*password*``, ``*token*``, ``*secret*``,
    ``*api_key*``, any case)."""
    return _SECRET_KEY.search(key) is not None


def redact_text(text: str) -> str:
    """``text`` with URL passwords (``scheme://user:***@host``) and secret ``key=value`` pairs masked."""
    text = _URL_PASSWORD.sub(lambda m: f"{m['head']}{REDACTED}@", text)
    return _SECRET_PAIR.sub(lambda m: f"{m['head']}{REDACTED}", text)


def redact(key: str, value: Any) -> Any:
    """``value`` as it may be logged under ``key``: :data:`REDACTED` when the key names a secret, strings masked
    by :func:`redact_text`, mappings and lists redacted item by item, anything else unchanged."""
    if is_secret_key(key) and value not in (None, ""):
        return REDACTED
    if isinstance(value, str):
        return redact_text(value)
    if isinstance(value, Mapping):
        return {k: redact(str(k), v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [redact(key, v) for v in value]
    return value


def loggable(params: Mapping[str, Any], limit: int = 500) -> dict[str, str]:
    """Params as MLflow strings: redacted first (a cut could split a password from its URL), then cut to
    ``limit`` characters."""
    return {key: str(redact(key, value))[:limit] for key, value in params.items()}


def log_params(params: Mapping[str, Any]) -> None:
    """Log params (redacted, see :func:`loggable`) to the active MLflow run."""
    mlflow.log_params(loggable(params))


def project_root(root: Path) -> Path:
    """Where the project's MLflow store lives: ``root``, or the repository DVC names in ``DVC_ROOT`` when it differs
    (a queued ``dvc exp run`` executes in a temporary copy that is deleted afterwards; DVC points ``DVC_ROOT`` at
    the repository it came from)."""
    dvc_root = os.environ.get("DVC_ROOT")
    return Path(dvc_root) if dvc_root else root


def tracking_uri(root: Path) -> str:
    """The tracking URI in effect for a project rooted at ``root``: ``MLFLOW_TRACKING_URI`` when set, else the
    sqlite file of :func:`project_root`."""
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{(project_root(root) / 'mlflow.db').resolve()}"


def git_commit(root: Path) -> str:
    """The current git commit of ``root``, or ``unknown`` outside a repository."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True, timeout=10
        )
        return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def flatten(params: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` for MLflow params."""
    flat: dict[str, Any] = {}
    for key, value in params.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(flatten(value, f"{name}."))
        else:
            flat[name] = value
    return flat


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


def params_digest(root: Path) -> str:
    """The first 12 hex digits of the SHA-256 of ``root/params.yaml`` (``none`` without one)."""
    path = root / "params.yaml"
    return hashlib.sha256(path.read_bytes()).hexdigest()[:12] if path.is_file() else "none"


def pipeline_identity(root: Path) -> tuple[str, str, dict[str, str]]:
    """``(key, run name, tags)`` of the pipeline run a stage belongs to. The rule, first match:

    1. ``ADAPTDIFFUSER_PIPELINE_RUN`` set: that name (a user's own grouping);
    2. ``DVC_EXP_NAME`` set (``dvc exp run``): the DVC experiment, with its baseline commit (``DVC_EXP_BASELINE_REV``);
    3. otherwise (``dvc repro``, a stage run by hand): the git commit and the digest of ``params.yaml``.

    The key is a digest of that identity (no secret in a name reaches it)."""
    commit, digest = git_commit(root), params_digest(root)
    tags = {"git_commit": commit, "params_digest": digest}
    if os.environ.get(PIPELINE_RUN_ENV):
        name = os.environ[PIPELINE_RUN_ENV]
        identity = f"name:{name}"
    elif os.environ.get("DVC_EXP_NAME"):
        exp, baseline = os.environ["DVC_EXP_NAME"], os.environ.get("DVC_EXP_BASELINE_REV", "")
        identity, name = f"dvc-exp:{baseline}:{exp}", f"exp-{exp}"
        tags |= {"dvc_exp_name": exp, "dvc_baseline_rev": baseline}
    else:
        identity, name = f"repro:{commit}:{digest}", f"repro-{commit[:7]}-params-{digest[:6]}"
    return hashlib.sha256(identity.encode()).hexdigest()[:16], name, tags


def pipeline_run(experiment_id: str, root: Path) -> str:
    """The id of the parent run of this pipeline run in the experiment (see :func:`pipeline_identity`): found by its
    :data:`PIPELINE_KEY_TAG`, else created (tags ``stage=pipeline``, the commit, the params digest and the DVC
    experiment; ``params.yaml`` as params). Stages run in separate processes, one after another; should two create
    it at once, the older run wins and the other is deleted."""
    client = MlflowClient()
    key, name, tags = pipeline_identity(root)
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
    run = client.create_run(experiment_id, run_name=redact_text(name), tags=loggable(tags, 5000))
    run_id = run.info.run_id
    winner = oldest()[0].info.run_id
    if winner != run_id:
        client.delete_run(run_id)
        return winner
    path = root / "params.yaml"
    raw = yaml.safe_load(path.read_text()) if path.is_file() else None
    if isinstance(raw, dict):
        logged = loggable(flatten(raw))
        for start in range(0, len(logged), 100):
            chunk = list(logged.items())[start : start + 100]
            client.log_batch(run_id, params=[Param(k, v) for k, v in chunk])
    return run_id


def stage_times(root: Path) -> list[dict[str, Any]]:
    """How long each stage run of this pipeline run took (:func:`pipeline_identity` at ``root``: this commit and
    params.yaml), over every task's experiment, in the order they started: task, run name, status, seconds."""
    root = root.resolve()
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


@contextmanager
def stage_run(
    task: str,
    stage: str,
    phase: int | None,
    params: dict[str, Any],
    root: Path = Path("."),
    seed: int | str | None = None,
) -> Iterator[Any]:
    """An MLflow run for one stage execution (for one training seed, when given; ``seed`` tag and a ``-seed<s>``
    run name; ``phase`` None: a stage over every phase, tag ``phase=all``), nested under the pipeline's parent run
    (:func:`pipeline_run`; a sweep trial's run inside a sweep). FAILED if the body raises, and so is the parent
    (FINISHED again when a later stage succeeds)."""
    root = root.resolve()
    mlflow.set_tracking_uri(tracking_uri(root))
    experiment_id = ensure_experiment(task, root)
    tags = {"stage": stage, "phase": "all" if phase is None else str(phase), "task": task}
    tags["git_commit"] = git_commit(root)
    name = stage if phase is None else f"{stage}-phase{phase}"
    if seed is not None:
        tags["seed"] = str(seed)
        name += f"-seed{seed}"
    if os.environ.get("DVC_EXP_NAME"):
        tags["dvc_exp_name"] = os.environ["DVC_EXP_NAME"]
    parent = None
    if os.environ.get(PARENT_RUN_ENV):  # a sweep trial: nest the stage's run under the trial's run
        tags["mlflow.parentRunId"] = os.environ[PARENT_RUN_ENV]
    else:
        parent = tags["mlflow.parentRunId"] = pipeline_run(experiment_id, root)
        MlflowClient().update_run(parent, status="RUNNING")
    status = "FAILED"
    try:
        with mlflow.start_run(experiment_id=experiment_id, run_name=name, tags=loggable(tags, 5000)) as run:
            log_params(flatten(params))
            yield run
        status = "FINISHED"
    finally:
        if parent is not None:
            MlflowClient().set_terminated(parent, status)


def log_dataset(path: Path, sha256: str, context: str, name: str) -> None:
    """Log the Parquet file ``path`` as a dataset input of the active run (an MLflow ``MetaDataset``: its name, its
    file as source and the first 32 hex digits of its SHA-256 as digest; nothing is read), in ``context``
    (``training``, ``synthetic-phase<j>``...)."""
    from mlflow.data.dataset_source_registry import get_registered_sources
    from mlflow.data.meta_dataset import MetaDataset

    local = next(cls for cls in get_registered_sources() if cls.__name__ == "LocalArtifactDatasetSource")
    dataset = MetaDataset(local(path.resolve().as_uri()), name=name, digest=sha256[:32])
    mlflow.log_input(dataset, context=context)


def registered_model_name(task: str) -> str:
    """The MLflow registered model holding a task's trained models: ``adaptdiffuser-<task>``."""
    return f"adaptdiffuser-{task}"


def log_model(
    model: Any, bundle_dir: Path, task: str, label: str, seed: int, primary: bool, tags: dict[str, str]
) -> str | None:
    """Log ``model`` (a torch module: the EMA diffusion model, its U-Net in ``.model``) to the active run with
    ``mlflow.pytorch`` (pickled, on the CPU; the ``config.json`` and ``normalizer.json`` of its checkpoint folder
    ``bundle_dir`` beside it), so that
    ``mlflow.pytorch.load_model`` gives it back; register it as a version of :func:`registered_model_name` with
    the aliases ``<label>-seed<s>`` and, for the ``primary`` (first) training seed, ``<label>`` (``phase1``,
    ``phase1-control``). Returns the version, or None inside a sweep trial (logged, not registered: trials must
    not move the aliases)."""
    import copy
    from importlib.metadata import version as package_version

    import mlflow.pytorch

    with _quiet_model_logging():
        info = mlflow.pytorch.log_model(
            copy.deepcopy(model).to("cpu"),
            name="model",
            serialization_format="pickle",
            pip_requirements=[f"torch=={package_version('torch')}"],  # no inference (it imports the model again)
            extra_files=[str(bundle_dir / name) for name in ("config.json", "normalizer.json")],
        )
        if os.environ.get(PARENT_RUN_ENV):
            return None
        return _register(info, task, label, seed, primary, tags)


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


def _register(info: Any, task: str, label: str, seed: int, primary: bool, tags: dict[str, str]) -> str:
    """Register the logged model ``info`` as a new version of the task's model, with its aliases."""
    client = MlflowClient()
    name = registered_model_name(task)
    try:
        client.get_registered_model(name)
    except MlflowException:
        with suppress(MlflowException):  # created meanwhile
            client.create_registered_model(name, description=f"AdaptDiffuser's EMA diffusion models of {task}")
    run_id = mlflow.active_run().info.run_id
    tags = loggable({"task": task, "label": label, "seed": seed, **tags})
    created = client.create_model_version(name, info.model_uri, run_id=run_id, tags=tags, model_id=info.model_id)
    client.set_registered_model_alias(name, f"{label}-seed{seed}", created.version)
    if primary:
        client.set_registered_model_alias(name, label, created.version)
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


def log_over_seeds(task: str, stage: str, phase: int, metrics: dict[str, Any], root: Path = Path(".")) -> None:
    """With several training seeds, one more run (``<stage>-phase<k>-seedall``, tag ``seed=all``) holding the
    aggregate of a stage's per-seed metrics (see :func:`adaptdiffuser.seed_metrics.over_seeds`)."""
    if metrics.get("n_seeds", 1) < 2:
        return
    numbers = {
        k: float(v)
        for k, v in flatten({k: v for k, v in metrics.items() if k != "seeds"}).items()
        if isinstance(v, int | float) and not isinstance(v, bool)
    }
    seeds = ",".join(metrics["seeds"])
    with stage_run(task, stage, phase, {"seeds": seeds}, root, seed="all"):
        mlflow.log_metrics(numbers)
