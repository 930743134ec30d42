"""Secrets never leave the process: a storage URL's password and the value of any ``*password*``, ``*token*``,
``*secret*`` or ``*api_key*`` key are redacted before anything reaches MLflow (stage runs, the sweep's parent run)
or an error message, while the rest (user, host, database) stays readable."""

from __future__ import annotations

from pathlib import Path

import mlflow
import pytest
from mlflow.tracking import MlflowClient

from adaptdiffuser.config import SweepParams
from adaptdiffuser.errors import StageError
from adaptdiffuser.tooling.mlflow_logging import (
    REDACTED,
    ensure_experiment,
    log_pending,
    redact,
    redact_text,
    stage_run,
)
from adaptdiffuser.tooling.optuna_sweep import make_storage, start_parent_run
from adaptdiffuser.tooling.run_records import PENDING

PASSWORD = "S3cr3t-pw"
STORAGE = f"postgresql://alice:{PASSWORD}@db.example.org:5432/optuna"
SECRETS = (PASSWORD, "hunter2", "k3y-abc", "t0k3n-xyz", "sh-secret")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (STORAGE, "postgresql://alice:***@db.example.org:5432/optuna"),
        ("postgresql+psycopg://alice:p%40ss@db/optuna", "postgresql+psycopg://alice:***@db/optuna"),
        ("postgresql://alice:p@ss/w0rd@db/optuna", "postgresql://alice:***@db/optuna"),  # unescaped @ and /
        ("redis://:pw@cache:6379/0", "redis://:***@cache:6379/0"),
        ("postgresql://alice@db.example.org/optuna", "postgresql://alice@db.example.org/optuna"),  # no password
        ("postgresql://db.example.org:5432/optuna", "postgresql://db.example.org:5432/optuna"),  # a port, not one
        (
            "postgresql://alice@db/optuna?password=hunter2&sslmode=require",
            "postgresql://alice@db/optuna?password=***&sslmode=require",
        ),
        ("host=db user=alice password=hunter2 dbname=optuna", "host=db user=alice password=*** dbname=optuna"),
        ('{"db_password": "hunter2", "steps": 3}', '{"db_password": "***", "steps": 3}'),
        ("sweeps/adaptdiffuser.journal", "sweeps/adaptdiffuser.journal"),
    ],
)
def test_redact_text_masks_passwords_and_keeps_the_rest(text: str, expected: str) -> None:
    assert redact_text(text) == expected


def test_redact_masks_secret_keys_at_any_depth() -> None:
    assert redact("db_password", "hunter2") == REDACTED
    assert redact("sweep.API_KEY", 12345) == REDACTED
    assert redact("github-Token", "t0k3n-xyz") == REDACTED
    assert redact("sweep", {"storage": STORAGE, "client_secret": "sh-secret", "trials": 4}) == {
        "storage": "postgresql://alice:***@db.example.org:5432/optuna",
        "client_secret": REDACTED,
        "trials": 4,
    }
    assert redact("urls", [STORAGE, 1]) == ["postgresql://alice:***@db.example.org:5432/optuna", 1]
    assert redact("alpha", 30.0) == 30.0 and redact("password", None) is None


def _everything_logged(client: MlflowClient, experiment_id: str, tmp_path: Path) -> list[str]:
    """Every run's name, params, tags and the text of its artifacts, one string per run."""
    logged = []
    for run in client.search_runs([experiment_id]):
        parts = [run.info.run_name or "", repr(run.data.params), repr(run.data.tags)]
        folder = Path(mlflow.artifacts.download_artifacts(run_id=run.info.run_id, dst_path=str(tmp_path / "dl")))
        parts += [p.read_text(errors="replace") for p in folder.rglob("*") if p.is_file()]
        logged.append("\n".join(parts))
    return logged


def test_no_secret_reaches_mlflow(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setenv("DVC_EXP_NAME", "exp-password=hunter2")  # a tag every stage run copies
    params = {
        "sweep": {"storage": STORAGE, "trials": 4},
        "db_password": "hunter2",
        "service": {"api_key": "k3y-abc", "url": "https://bot:t0k3n-xyz@api.example.org/v1"},
        "alpha": 30.0,
    }
    try:
        with stage_run("maze2d-umaze", "pretrain", 0, params, tmp_path, seed=0) as run:
            run.log_params({"client_secret": "sh-secret", "data.sha256": "ab" * 32})
        for record in (tmp_path / PENDING).rglob("*"):  # nor the record the stage leaves for MLflow
            if record.is_file():
                assert not [secret for secret in SECRETS if secret in record.read_text()]
        log_pending(tmp_path)
        client = MlflowClient(uri)
        experiment_id = ensure_experiment("maze2d-umaze", tmp_path)
        sweep = SweepParams(study="secret-study", space={"alpha": {"low": 1.0, "high": 100.0, "log": True}})
        parent_id = start_parent_run(client, experiment_id, sweep, "maze2d-umaze", STORAGE, 4, 2)
        client.set_terminated(parent_id)

        logged = _everything_logged(client, experiment_id, tmp_path)
        assert len(logged) == 3  # the stage's run, its pipeline run (named after the DVC experiment), the sweep's
        for text in logged:
            assert not [secret for secret in SECRETS if secret in text]
        (stage,) = client.search_runs([experiment_id], "tags.stage = 'pretrain'")
        assert stage.data.params["sweep.storage"] == "postgresql://alice:***@db.example.org:5432/optuna"
        assert stage.data.params["db_password"] == REDACTED and stage.data.params["service.api_key"] == REDACTED
        assert stage.data.params["service.url"] == "https://bot:***@api.example.org/v1"
        assert stage.data.params["alpha"] == "30.0" and stage.data.params["data.sha256"] == "ab" * 32
        assert stage.data.tags["dvc_exp_name"] == "exp-password=***"
        parent = client.get_run(parent_id)
        assert parent.data.tags["storage"] == "postgresql://alice:***@db.example.org:5432/optuna"
        assert parent.data.params["space.alpha"] == "float [1, 100] log"
    finally:
        mlflow.set_tracking_uri(None)


def test_a_storage_that_cannot_be_opened_is_named_without_its_password(tmp_path: Path) -> None:
    url = f"postgresql://alice:{PASSWORD}@127.0.0.1:1/optuna"  # nothing listens on port 1
    with pytest.raises(StageError) as err:
        make_storage(url, tmp_path, "study", 30)
    message = str(err.value)
    assert "postgresql://alice:***@127.0.0.1:1/optuna" in message and PASSWORD not in message
    assert err.value.__cause__ is None and err.value.__suppress_context__  # no chained traceback to print
