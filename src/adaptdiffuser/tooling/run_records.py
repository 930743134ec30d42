"""Stage run records: what a stage logs to MLflow, written beside the project without importing MLflow.

Importing MLflow and opening its SQLite store costs a process about 4.7 CPU-s, more than most smoke stages work.
So a stage records its run in a folder of ``<project>/mlflow-pending/`` (:func:`stage_run`): tags, params (redacted),
metrics with their steps and times, dataset inputs, copies of its artifacts and its models, its start and end time
and status, and the pipeline run it belongs to (:func:`pipeline_identity`). One process later logs every pending
record to MLflow in start order (:func:`adaptdiffuser.tooling.mlflow_logging.log_pending`: the summarize stage, a
sweep worker after each trial, ``adaptdiffuser mlflow-log`` by hand), as the stage itself used to.

A record appears whole or not at all: it is built in a hidden ``.<id>.tmp`` folder and renamed to ``<id>`` (start
time in nanoseconds, then a random suffix, so names sort in start order) when the stage ends, FAILED if it raised,
KILLED if SIGTERM stopped it (:class:`_RecordOnSigterm`: the record is written, then the signal ends the process as it
would have). The hidden folder holds the writer's host and pid (:data:`WRITER_FILE`): the one of a process that no
longer runs (SIGKILL, out of memory) is deleted by :func:`remove_dead_partials`.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any

import yaml

#: set by a sweep worker to the MLflow run id of the current trial
PARENT_RUN_ENV = "ADAPTDIFFUSER_PARENT_RUN_ID"
#: names the pipeline run (parent run) the stages nest under, overriding the rule of :func:`pipeline_identity`
PIPELINE_RUN_ENV = "ADAPTDIFFUSER_PIPELINE_RUN"
#: the tag that finds a pipeline run's parent run again from the next stage's process
PIPELINE_KEY_TAG = "pipeline_key"
#: the ``stage`` tag of a pipeline's parent run
PIPELINE_STAGE = "pipeline"
#: the folder (under :func:`project_root`) holding the records not yet logged to MLflow
PENDING = "mlflow-pending"
#: a record's description inside its folder
RECORD_FILE = "record.json"
#: ``{"host": ..., "pid": ...}`` of the process writing a hidden ``.<id>.tmp`` record folder
WRITER_FILE = "writer.json"

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


def project_root(root: Path) -> Path:
    """Where the project's MLflow store (and its pending records) live: ``root``, or the repository DVC names in
    ``DVC_ROOT`` when it differs (a queued ``dvc exp run`` executes in a temporary copy that is deleted afterwards;
    DVC points ``DVC_ROOT`` at the repository it came from)."""
    dvc_root = os.environ.get("DVC_ROOT")
    return Path(dvc_root) if dvc_root else root


def pending_root(root: Path) -> Path:
    """The folder of the records not yet logged to MLflow: ``<project_root>/mlflow-pending``."""
    return project_root(root) / PENDING


def pending_records(root: Path) -> list[Path]:
    """The complete records waiting in :func:`pending_root`, oldest start first (hidden folders, records still being
    written or being deleted, are left out)."""
    folder = pending_root(root)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if not p.name.startswith(".") and (p / RECORD_FILE).is_file())


def _runs(pid: int) -> bool:
    """Whether a process ``pid`` runs on this host (one of another user counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_dead_partials(root: Path) -> list[str]:
    """Delete the hidden ``.<id>.tmp`` folders of :func:`pending_root` whose writer (:data:`WRITER_FILE`) was a
    process of this host that no longer runs: a stage killed by SIGKILL or out of memory, whose record can never be
    whole. A folder of a live process, of another host or without a writer file is left alone. The names deleted."""
    folder = pending_root(root)
    removed = []
    for partial in sorted(folder.glob(".*.tmp")) if folder.is_dir() else []:
        try:
            writer = json.loads((partial / WRITER_FILE).read_text())
            dead = writer["host"] == socket.gethostname() and not _runs(int(writer["pid"]))
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if dead:
            shutil.rmtree(partial, ignore_errors=True)
            removed.append(partial.name)
    return removed


def git_commit(root: Path) -> str:
    """The current git commit of ``root``, or ``unknown`` outside a repository."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True, timeout=10
        )
        return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


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


def pipeline_record(root: Path) -> dict[str, Any]:
    """What the parent run of this stage's pipeline run needs (:func:`pipeline_identity`): its key, name (redacted)
    and tags, and ``root/params.yaml`` as redacted params."""
    key, name, tags = pipeline_identity(root)
    path = root / "params.yaml"
    raw = yaml.safe_load(path.read_text()) if path.is_file() else None
    params = loggable(flatten(raw)) if isinstance(raw, dict) else {}
    return {"key": key, "name": redact_text(name), "tags": loggable(tags, 5000), "params": params}


def _now_ms() -> int:
    return time.time_ns() // 1_000_000


class StageRecord:
    """One stage execution's MLflow run, recorded in a folder: the part of MLflow's logging API the stages use."""

    def __init__(self, folder: Path, data: dict[str, Any]) -> None:
        self.folder = folder  # the hidden folder being written
        self.data = data

    @property
    def id(self) -> str:
        """The record's name in the pending folder (and its MLflow run's ``record_id`` tag)."""
        return str(self.data["id"])

    def log_params(self, params: Mapping[str, Any]) -> None:
        """Params (redacted, see :func:`loggable`)."""
        self.data["params"].update(loggable(params))

    def log_metric(self, key: str, value: float, step: int = 0) -> None:
        """One metric value at ``step``, stamped with the time now."""
        self.data["metrics"].append({"key": key, "value": float(value), "step": int(step), "timestamp": _now_ms()})

    def log_metrics(self, metrics: Mapping[str, float], step: int = 0) -> None:
        """Several metric values at ``step``."""
        for key, value in metrics.items():
            self.log_metric(key, value, step)

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        """Tags (redacted)."""
        self.data["tags"].update(loggable(tags, 5000))

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        """A copy of the file ``path`` as an artifact (under ``artifact_path``), taken now: the file may change or
        vanish before the record is logged."""
        target = self.folder / "artifacts" / (artifact_path or "")
        target.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, target / Path(path).name)

    def log_artifacts(self, local_dir: str | Path, artifact_path: str | None = None) -> None:
        """A copy of the folder ``local_dir``'s files as artifacts (under ``artifact_path``)."""
        shutil.copytree(local_dir, self.folder / "artifacts" / (artifact_path or ""), dirs_exist_ok=True)

    def log_dataset(self, path: Path, sha256: str, context: str, name: str) -> None:
        """The Parquet file ``path`` as a dataset input (an MLflow ``MetaDataset``: its name, its file as source and
        the first 32 hex digits of ``sha256`` as digest; nothing is read), in ``context`` (``training``,
        ``synthetic-phase<j>``...)."""
        source = Path(path).resolve().as_uri()
        self.data["datasets"].append({"source": source, "digest": sha256[:32], "context": context, "name": name})

    def log_model(
        self, model: Any, bundle_dir: Path, task: str, label: str, seed: int, primary: bool, tags: Mapping[str, Any]
    ) -> None:
        """``model`` (a torch module: the EMA diffusion model) saved on the CPU, with the ``config.json`` and
        ``normalizer.json`` of its checkpoint folder ``bundle_dir``, to be logged with ``mlflow.pytorch`` and
        registered as a version of ``adaptdiffuser-<task>`` aliased ``<label>-seed<s>`` (and ``<label>`` when
        ``primary``); inside a sweep trial it is logged, not registered (trials must not move the aliases)."""
        import copy

        import torch

        folder = self.folder / "models" / str(len(self.data["models"]))
        folder.mkdir(parents=True)
        torch.save(copy.deepcopy(model).to("cpu"), folder / "model.pt")
        extra = []
        for name in ("config.json", "normalizer.json"):
            shutil.copy2(Path(bundle_dir) / name, folder / name)
            extra.append(name)
        self.data["models"].append({
            "folder": folder.relative_to(self.folder).as_posix(), "extra_files": extra, "task": task,
            "label": label, "seed": seed, "primary": primary, "register": self.data["parent_run_id"] is None,
            "tags": loggable({"task": task, "label": label, "seed": seed, **tags}),
        })  # fmt: skip

    def set_best_alias(self, task: str, phase: int) -> None:
        """Point the alias ``best`` of the task's registered model at the version aliased ``phase<k>`` once the
        models before it are logged; the run gets the tag ``best_model_version`` (``None`` without one)."""
        self.data["best_alias"] = {"task": task, "phase": phase}

    def finish(self, status: str) -> Path:
        """Write the record and move it into the pending folder, whole; its final folder."""
        from adaptdiffuser.io import write_json

        self.data |= {"status": status, "end_ms": _now_ms()}
        write_json(self.folder / RECORD_FILE, self.data)
        final = self.folder.with_name(self.id)
        os.replace(self.folder, final)
        self.folder = final
        return final


class _RecordOnSigterm:
    """SIGTERM's handler while a stage runs (installed only over the default one): write the record KILLED, put the
    former handler back and send SIGTERM again, so that the process still ends by the signal (or the handler of an
    enclosing :func:`stage_run` writes its record in turn). A signal that arrives while the record is already being
    written waits for the end of that (:attr:`received`). A forked child (a data loader's worker), which inherits the
    handler and gets the SIGTERM of the process group too, writes nothing: the signal takes its former course there.
    """

    def __init__(self, record: StageRecord, previous: Any) -> None:
        self.record, self.previous = record, previous
        self.pid = os.getpid()
        self.closing = False  # the record is being written, or was
        self.received = False

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        if os.getpid() != self.pid:
            signal.signal(signal.SIGTERM, self.previous)
            os.kill(os.getpid(), signal.SIGTERM)
            return
        if self.closing:
            self.received = True
            return
        self.closing = True
        signal.signal(signal.SIGTERM, self.previous)
        try:
            self.record.finish("KILLED")
        finally:
            os.kill(os.getpid(), signal.SIGTERM)


def read_record(folder: Path) -> dict[str, Any]:
    """The description of the record in ``folder``."""
    return json.loads((folder / RECORD_FILE).read_text())


@contextmanager
def stage_run(
    task: str,
    stage: str,
    phase: int | None,
    params: dict[str, Any],
    root: Path = Path("."),
    seed: int | str | None = None,
) -> Iterator[StageRecord]:
    """A record of the MLflow run of one stage execution (for one training seed, when given; ``seed`` tag and a
    ``-seed<s>`` run name; ``phase`` None: a stage over every phase, tag ``phase=all``), nested under the pipeline's
    parent run (:func:`pipeline_identity`; a sweep trial's run inside a sweep). FAILED if the body raises, and so is
    the parent (FINISHED again when a later stage succeeds). Written to :func:`pending_root` when the body ends."""
    root = root.resolve()
    start_ms = _now_ms()
    tags = {"stage": stage, "phase": "all" if phase is None else str(phase), "task": task}
    tags["git_commit"] = git_commit(root)
    name = stage if phase is None else f"{stage}-phase{phase}"
    if seed is not None:
        tags["seed"] = str(seed)
        name += f"-seed{seed}"
    if os.environ.get("DVC_EXP_NAME"):
        tags["dvc_exp_name"] = os.environ["DVC_EXP_NAME"]
    parent = os.environ.get(PARENT_RUN_ENV) or None  # a sweep trial: nest the stage's run under the trial's run
    record_id = f"{time.time_ns():020d}-{secrets.token_hex(4)}"
    folder = pending_root(root) / f".{record_id}.tmp"
    folder.mkdir(parents=True)
    (folder / WRITER_FILE).write_text(json.dumps({"host": socket.gethostname(), "pid": os.getpid()}))
    data: dict[str, Any] = {
        "id": record_id, "task": task, "run_name": name, "tags": loggable(tags, 5000), "params": {},
        "metrics": [], "datasets": [], "models": [], "best_alias": None, "parent_run_id": parent,
        "pipeline": None if parent else pipeline_record(root), "start_ms": start_ms,
    }  # fmt: skip
    record = StageRecord(folder, data)
    record.log_params(flatten(params))
    guard = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.getsignal(signal.SIGTERM)
        if previous is signal.SIG_DFL or isinstance(previous, _RecordOnSigterm):
            guard = _RecordOnSigterm(record, previous)
            signal.signal(signal.SIGTERM, guard)
    status = "FAILED"
    try:
        yield record
        status = "FINISHED"
    finally:
        if guard is None:
            record.finish(status)
        elif not guard.closing:  # else the handler wrote it KILLED (and the process ends by SIGTERM)
            guard.closing = True
            try:
                record.finish(status)
            finally:
                signal.signal(signal.SIGTERM, guard.previous)
                if guard.received:  # SIGTERM while the record was written: its course now
                    os.kill(os.getpid(), signal.SIGTERM)


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
    with stage_run(task, stage, phase, {"seeds": seeds}, root, seed="all") as run:
        run.log_metrics(numbers)
