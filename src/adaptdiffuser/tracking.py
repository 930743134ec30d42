"""MLflow tracking: one experiment per task, one run per stage execution (and training seed), tagged with stage,
phase and seed.

The tracking URI defaults to ``sqlite:///<repo>/mlflow.db`` (``MLFLOW_TRACKING_URI`` overrides it) and each
experiment stores artifacts under an explicit absolute location, ``<repo>/mlartifacts/<task>``. A stage that
raises leaves its run marked FAILED.

Secrets never reach MLflow: every param and tag goes through :func:`redact` (the password of a URL such as
``postgresql://user:PASSWORD@host/db``, and the value of any key like ``*password*``, ``*token*``, ``*secret*`` or
``*api_key*``, become ``***``).
"""

from __future__ import annotations

import os
import re
import subprocess
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import mlflow

#: set by a sweep worker to the MLflow run id of the current trial
PARENT_RUN_ENV = "ADAPTDIFFUSER_PARENT_RUN_ID"

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


def tracking_uri(root: Path) -> str:
    """The tracking URI in effect for a project rooted at ``root``."""
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{(root / 'mlflow.db').resolve()}"


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
    """The id of the task's experiment, created with an absolute artifact location if new."""
    experiment = mlflow.get_experiment_by_name(task)
    if experiment is not None:
        return experiment.experiment_id
    location = (root / "mlartifacts" / task).resolve().as_uri()
    return mlflow.create_experiment(task, artifact_location=location)


@contextmanager
def stage_run(
    task: str, stage: str, phase: int, params: dict[str, Any], root: Path = Path("."), seed: int | str | None = None
) -> Iterator[Any]:
    """An MLflow run for one stage execution (for one training seed, when given; ``seed`` tag and a ``-seed<s>``
    run name); FAILED if the body raises."""
    root = root.resolve()
    mlflow.set_tracking_uri(tracking_uri(root))
    experiment_id = ensure_experiment(task, root)
    tags = {"stage": stage, "phase": str(phase), "task": task, "git_commit": git_commit(root)}
    name = f"{stage}-phase{phase}"
    if seed is not None:
        tags["seed"] = str(seed)
        name += f"-seed{seed}"
    if os.environ.get("DVC_EXP_NAME"):
        tags["dvc_exp_name"] = os.environ["DVC_EXP_NAME"]
    if os.environ.get(PARENT_RUN_ENV):  # a sweep trial: nest the stage's run under the trial's run
        tags["mlflow.parentRunId"] = os.environ[PARENT_RUN_ENV]
    with mlflow.start_run(experiment_id=experiment_id, run_name=name, tags=loggable(tags, 5000)) as run:
        log_params(flatten(params))
        yield run


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
