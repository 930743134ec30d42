"""Stage run records (:mod:`adaptdiffuser.tooling.run_records`) logged to a real MLflow SQLite store by
:func:`~adaptdiffuser.tooling.mlflow_logging.log_pending`: the run a stage used to log itself, once, with a crash
halfway through neither losing nor doubling a record; and a stage that imports no MLflow."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import mlflow
import mlflow.pytorch
import pytest
import torch
from mlflow.tracking import MlflowClient

from adaptdiffuser.tooling.mlflow_logging import RECORD_ID_TAG, _log_record, log_pending, registered_model_name
from adaptdiffuser.tooling.run_records import (
    PARENT_RUN_ENV,
    PENDING,
    PIPELINE_RUN_ENV,
    pending_records,
    read_record,
    stage_run,
)

TASK = "maze2d-umaze"


@pytest.fixture
def store(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> MlflowClient:
    """A project folder with params.yaml and its own SQLite store (``MLFLOW_TRACKING_URI``)."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    for name in ("DVC_EXP_NAME", "DVC_ROOT", PIPELINE_RUN_ENV, PARENT_RUN_ENV):
        monkeypatch.delenv(name, raising=False)
    (tmp_path / "params.yaml").write_text("alpha: 1\nsweep: {storage: 'postgresql://u:hunter2@db/x'}\n")
    yield MlflowClient(uri)
    mlflow.set_tracking_uri(None)


def _pretrain(root: Path, model: torch.nn.Module) -> str:
    """Record a pretrain-like stage run in ``root``: params, a loss curve, files, a dataset and a model."""
    out = root / "models" / "seed0"
    out.mkdir(parents=True)
    (out / "config.json").write_text("{}")
    (out / "normalizer.json").write_text("{}")
    (root / "plan.png").write_bytes(b"png")
    with stage_run(TASK, "pretrain", 0, {"pretrain": {"steps": 20}, "db_password": "hunter2"}, root, seed=0) as run:
        run.log_dataset(root / "data.parquet", "ab" * 32, "training", "data/dataset.parquet")
        for step in (5, 10):
            run.log_metric("train_loss", 1.0 / step, step=step)
        run.log_metrics({"windows": 7})
        run.log_artifacts(out, artifact_path="checkpoint")
        run.log_artifact(root / "plan.png", artifact_path="plans")
        run.log_model(model, out, TASK, "phase0", 0, True, {"stage": "pretrain"})
    (root / "plan.png").unlink()  # an output a later stage replaces: the record kept its own copy
    return run.id


def test_a_logged_record_is_the_run_the_stage_logged_before_and_is_logged_once(
    store: MlflowClient, tmp_path: Path
) -> None:
    model = torch.nn.Linear(3, 2)
    pretrain_id = _pretrain(tmp_path, model)
    with stage_run(TASK, "summarize", None, {"phases": "0"}, tmp_path) as run:
        run.log_metric("score", 12.5, step=0)
        run.set_tags({"best_phase": "0"})
        run.set_best_alias(TASK, 0)
    record = read_record(pending_records(tmp_path)[0])
    assert "hunter2" not in json.dumps(record) and record["status"] == "FINISHED"

    logged = log_pending(tmp_path)
    assert list(logged) == [pretrain_id, run.id] and pending_records(tmp_path) == []
    experiment = store.get_experiment_by_name(TASK)
    pretrain = store.get_run(logged[pretrain_id])
    assert pretrain.info.status == "FINISHED" and pretrain.info.run_name == "pretrain-phase0-seed0"
    assert pretrain.info.start_time == record["start_ms"] and pretrain.info.end_time == record["end_ms"]
    assert pretrain.data.params["pretrain.steps"] == "20" and pretrain.data.params["db_password"] == "***"
    assert pretrain.data.tags["stage"] == "pretrain" and pretrain.data.tags["seed"] == "0"
    assert pretrain.data.tags[RECORD_ID_TAG] == pretrain_id
    assert [(m.step, m.value) for m in store.get_metric_history(pretrain.info.run_id, "train_loss")] == [
        (5, 0.2),
        (10, 0.1),
    ]
    assert pretrain.data.metrics["windows"] == 7
    files = {a.path for folder in ("checkpoint", "plans") for a in store.list_artifacts(pretrain.info.run_id, folder)}
    assert files == {"checkpoint/config.json", "checkpoint/normalizer.json", "plans/plan.png"}
    (dataset,) = pretrain.inputs.dataset_inputs
    assert dataset.dataset.name == "data/dataset.parquet" and dataset.dataset.digest == "ab" * 16
    assert {t.key: t.value for t in dataset.tags}["mlflow.data.context"] == "training"
    # the pipeline's parent run: found by its key, params.yaml redacted, FINISHED with its last stage
    parent = store.get_run(pretrain.data.tags["mlflow.parentRunId"])
    assert parent.data.tags["stage"] == "pipeline" and parent.info.status == "FINISHED"
    assert parent.data.params == {"alpha": "1", "sweep.storage": "postgresql://u:***@db/x"}
    summarize = store.get_run(logged[run.id])
    assert summarize.data.tags["mlflow.parentRunId"] == parent.info.run_id
    # the registered model, its aliases (``best`` from the summarize record), and the model itself
    name = registered_model_name(TASK)
    version = store.get_model_version_by_alias(name, "best")
    assert set(store.get_registered_model(name).aliases) == {"phase0", "phase0-seed0", "best"}
    assert version.run_id == pretrain.info.run_id and summarize.data.tags["best_model_version"] == str(version.version)
    loaded = mlflow.pytorch.load_model(f"models:/{name}@best")
    assert torch.equal(loaded.weight, model.weight)

    assert log_pending(tmp_path) == {}  # nothing twice
    assert len(store.search_runs([experiment.experiment_id])) == 3
    assert len(store.search_model_versions(f"name = '{name}'")) == 1


def test_a_crash_while_logging_neither_loses_nor_doubles_a_record(store: MlflowClient, tmp_path: Path) -> None:
    with stage_run(TASK, "collect", 0, {"a": 1}, tmp_path) as run:
        run.log_metric("m", 1.0)
    # a flusher killed after creating the run, before its metrics and end: a run with the record's id, half-logged
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    experiment_id = mlflow.create_experiment(TASK)
    store.create_run(experiment_id, tags={RECORD_ID_TAG: run.id, "stage": "collect"})
    logged = log_pending(tmp_path)
    (collect,) = store.search_runs([experiment_id], "tags.stage = 'collect'")
    assert collect.info.run_id == logged[run.id] and collect.data.metrics == {"m": 1.0}
    assert collect.info.status == "FINISHED"
    # a flusher killed after logging the run whole, before deleting the record: the record goes, no second run
    with stage_run(TASK, "reference", 0, {}, tmp_path) as again:
        pass
    (folder,) = pending_records(tmp_path)
    whole = _log_record(folder, tmp_path)
    assert log_pending(tmp_path) == {again.id: whole} and pending_records(tmp_path) == []
    assert len(store.search_runs([experiment_id], "tags.stage = 'reference'")) == 1


def test_a_failed_stage_leaves_a_failed_record_and_a_sweep_trial_nests_under_its_trial(
    store: MlflowClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with pytest.raises(RuntimeError, match="boom"), stage_run(TASK, "pretrain", 0, {}, tmp_path):
        raise RuntimeError("boom")
    assert not any(p.name.startswith(".") and p.name != ".lock" for p in (tmp_path / PENDING).iterdir())
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    experiment_id = mlflow.create_experiment(TASK)
    trial = store.create_run(experiment_id, tags={"sweep": "s"}).info.run_id
    monkeypatch.setenv(PARENT_RUN_ENV, trial)
    with stage_run(TASK, "generate", 1, {}, tmp_path) as run:
        pass
    logged = log_pending(tmp_path)
    runs = {r.data.tags.get("stage", "trial"): r for r in store.search_runs([experiment_id])}
    assert runs["pretrain"].info.status == "FAILED" and runs["pipeline"].info.status == "FAILED"
    assert store.get_run(logged[run.id]).data.tags["mlflow.parentRunId"] == trial


def test_importing_a_stage_imports_no_mlflow_and_the_report_stage_no_torch() -> None:
    """Only the process that logs the records pays for MLflow's import (about 2.7 CPU-s), and a stage that needs no
    torch does not pay for its import either (about 2.2 CPU-s)."""
    stages = sorted(p.stem for p in (Path(__file__).parents[1] / "src/adaptdiffuser/stages").glob("[!_]*.py"))
    code = (
        "import sys, importlib, adaptdiffuser.cli, adaptdiffuser.stages.report\n"
        "print('torch' in sys.modules)\n"
        f"for name in {stages!r}: importlib.import_module('adaptdiffuser.stages.' + name)\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('mlflow', 'sqlalchemy')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split("\n")[:2] == ["False", "[]"] and len(stages) > 10


def test_the_mlflow_log_command_logs_what_a_failed_pipeline_left(
    store: MlflowClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """After a pipeline that stopped before ``summarize``, ``adaptdiffuser mlflow-log`` logs its records by hand."""
    from typer.testing import CliRunner

    from adaptdiffuser.cli import app

    with pytest.raises(RuntimeError), stage_run(TASK, "evaluate", 1, {}, tmp_path, seed=0):
        raise RuntimeError("boom")
    monkeypatch.chdir(tmp_path)
    out = CliRunner().invoke(app, ["mlflow-log"])
    assert out.exit_code == 0 and out.output.startswith("logged 1 stage run(s) to sqlite:///"), out.output
    (run,) = store.search_runs([store.get_experiment_by_name(TASK).experiment_id], "tags.stage = 'evaluate'")
    assert run.info.status == "FAILED" and pending_records(tmp_path) == []
    assert CliRunner().invoke(app, ["mlflow-log"]).output.startswith("logged 0 stage run(s)")


def test_pending_records_are_ignored_by_git_and_dvc(tmp_path: Path) -> None:
    """Whole records and the hidden folder of one being written are neither committed nor seen by DVC."""
    repo = Path(__file__).resolve().parents[1]
    for name in (".gitignore", ".dvcignore"):
        (tmp_path / name).write_text((repo / name).read_text())
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}", DVC_NO_ANALYTICS="1")
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True, env=env)
    subprocess.run(["dvc", "init", "-q"], cwd=tmp_path, check=True, env=env)
    paths = [f"{PENDING}/0001-ab/record.json", f"{PENDING}/.0002-cd.tmp/models/0/model.pt", f"{PENDING}/.lock"]
    for rel in paths:
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("x")
    for tool in ("git", "dvc"):
        for rel in paths:
            assert subprocess.run([tool, "check-ignore", "-q", rel], cwd=tmp_path, env=env).returncode == 0, (tool, rel)


STOPPED_CHILD = """
import sys, time
from pathlib import Path
from adaptdiffuser.stop_signals import DeferredStop
from adaptdiffuser.tooling.run_records import stage_run

root, deferred = Path(sys.argv[1]), sys.argv[2] == "deferred"
with stage_run("maze2d-umaze", "pretrain", 0, {}, root, seed=0) as run:
    run.log_metric("train_loss", 0.5, step=1)
    if deferred:  # a training loop that keeps a resume state: the step ends, then the signal takes its course
        with DeferredStop() as stop:
            print("ready", flush=True)
            while stop.received is None:
                time.sleep(0.01)
            run.log_metric("train_loss", 0.25, step=2)
            stop.deliver()
    print("ready", flush=True)
    time.sleep(60)
print("not reached", flush=True)
"""


@pytest.mark.parametrize("loop", ["plain", "deferred"])
def test_a_stage_stopped_by_sigterm_ends_by_it_with_its_record_written_killed(
    store: MlflowClient, tmp_path: Path, loop: str
) -> None:
    """`adaptdiffuser run stop` (SIGTERM) on a stage, with or without a training loop's DeferredStop inside: the
    process still ends by the signal, and its record, metrics so far, is written KILLED and logged KILLED."""
    import signal

    (tmp_path / "child.py").write_text(STOPPED_CHILD)
    child = subprocess.Popen(
        [sys.executable, str(tmp_path / "child.py"), str(tmp_path), loop],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    assert child.stdout is not None
    assert child.stdout.readline().strip() == "ready"
    child.send_signal(signal.SIGTERM)
    rest, _ = child.communicate(timeout=60)
    assert child.returncode == -signal.SIGTERM and "not reached" not in rest, rest
    (folder,) = pending_records(tmp_path)
    record = read_record(folder)
    steps = [(m["step"], m["value"]) for m in record["metrics"]]
    assert record["status"] == "KILLED" and steps == ([(1, 0.5)] if loop == "plain" else [(1, 0.5), (2, 0.25)])
    assert [p.name for p in (tmp_path / PENDING).iterdir() if p.name.endswith(".tmp")] == []

    logged = log_pending(tmp_path)
    run = store.get_run(logged[record["id"]])
    assert run.info.status == "KILLED" and run.info.end_time == record["end_ms"]
    assert [m.value for m in store.get_metric_history(run.info.run_id, "train_loss")] == [s[1] for s in steps]
    assert store.get_run(run.data.tags["mlflow.parentRunId"]).info.status == "KILLED"


def test_a_stage_ended_normally_gives_sigterm_back_to_its_former_handler_and_a_forked_child_writes_nothing(
    tmp_path: Path,
) -> None:
    """A forked child (a data loader's worker) gets the process group's SIGTERM too: it ends by it, and the record
    stays the stage's own, written when the stage ends."""
    import signal

    before = signal.getsignal(signal.SIGTERM)
    with stage_run(TASK, "collect", 0, {}, tmp_path) as run:
        assert signal.getsignal(signal.SIGTERM) is not before  # the record writer, over the default
        ready, told = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: waits for its SIGTERM (the fork's own start forgets a signal that came earlier)
            os.write(told, b"r")
            while True:
                signal.pause()
        assert os.read(ready, 1) == b"r"
        os.kill(pid, signal.SIGTERM)
        _, status = os.waitpid(pid, 0)
        assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGTERM
        assert (tmp_path / PENDING / f".{run.id}.tmp").is_dir() and pending_records(tmp_path) == []
        run.log_metric("m", 1.0)
    assert signal.getsignal(signal.SIGTERM) is before
    assert read_record(pending_records(tmp_path)[0])["status"] == "FINISHED"


def test_log_pending_deletes_the_hidden_folders_of_dead_writers_only(tmp_path: Path) -> None:
    """A stage killed by SIGKILL (or out of memory) leaves its hidden folder; the next logger deletes it, not the
    folder of a stage that still runs, of another host, or without a writer file."""
    import socket

    from adaptdiffuser.tooling.run_records import WRITER_FILE

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    host = socket.gethostname()
    writers = {"dead": (host, int(dead.stdout)), "live": (host, os.getpid()), "other-host": (f"{host}-x", 1)}
    for name, (writer_host, pid) in writers.items():
        partial = tmp_path / PENDING / f".{name}.tmp"
        partial.mkdir(parents=True)
        (partial / WRITER_FILE).write_text(json.dumps({"host": writer_host, "pid": pid}))
    (tmp_path / PENDING / ".no-writer.tmp").mkdir()
    assert log_pending(tmp_path) == {}
    left = sorted(p.name for p in (tmp_path / PENDING).iterdir())
    assert left == [".live.tmp", ".no-writer.tmp", ".other-host.tmp"]


def test_a_record_that_cannot_be_logged_is_set_aside_and_the_others_are_logged(
    store: MlflowClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """An unreadable record.json and a model whose class no longer unpickles go to mlflow-pending/.failed/ with their
    error, one warning line each, and never stop the good record nor the next `summarize`."""
    from adaptdiffuser.tooling.mlflow_logging import FAILED_DIR

    (tmp_path / "gone_model.py").write_text("import torch\nclass Gone(torch.nn.Linear):\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import gone_model  # a model class that a later commit renames

    out = tmp_path / "bundle"
    out.mkdir()
    for name in ("config.json", "normalizer.json"):
        (out / name).write_text("{}")
    with stage_run(TASK, "pretrain", 0, {}, tmp_path, seed=0) as gone:
        gone.log_model(gone_model.Gone(2, 2), out, TASK, "phase0", 0, True, {})
    monkeypatch.delitem(sys.modules, "gone_model")
    (tmp_path / "gone_model.py").unlink()
    with stage_run(TASK, "collect", 0, {}, tmp_path) as corrupt:
        pass
    (tmp_path / PENDING / corrupt.id / "record.json").write_text('{"id": ')
    with stage_run(TASK, "reference", 0, {}, tmp_path) as good:
        good.log_metric("m", 2.0)

    logged = log_pending(tmp_path)
    assert list(logged) == [good.id] and sorted(logged.failed) == sorted([gone.id, corrupt.id])
    assert store.get_run(logged[good.id]).data.metrics == {"m": 2.0} and pending_records(tmp_path) == []
    warnings = capsys.readouterr().err.strip().splitlines()
    assert len(warnings) == 2 and all(line.startswith("warning: run record ") for line in warnings)
    assert "ModuleNotFoundError" in logged.failed[gone.id] and "unreadable" in logged.failed[corrupt.id]
    for record_id in (gone.id, corrupt.id):
        error = (tmp_path / PENDING / FAILED_DIR / record_id / "error.txt").read_text()
        assert error.strip() == logged.failed[record_id]
    runs = store.search_runs([store.get_experiment_by_name(TASK).experiment_id])
    assert sorted(r.data.tags["stage"] for r in runs) == ["pipeline", "reference"]
    again = log_pending(tmp_path)
    assert again == {} and again.failed == {}


def test_an_unreachable_store_raises_and_leaves_every_record_waiting(
    store: MlflowClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with stage_run(TASK, "collect", 0, {}, tmp_path):
        pass
    # a database under a file: no store at all
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'params.yaml' / 'mlflow.db'}")
    with pytest.raises(Exception):  # noqa: B017, PT011 - whatever the store raises, it is no record's error
        log_pending(tmp_path)
    assert len(pending_records(tmp_path)) == 1 and not (tmp_path / PENDING / ".failed").exists()


def test_the_parent_run_ends_after_a_crash_before_it_and_at_its_last_stage_end(
    store: MlflowClient, tmp_path: Path
) -> None:
    """A logger that crashed after ending a stage's run but before ending the parent leaves it RUNNING: the retry
    ends it. Its end is the latest stage end, not that of the stage that started last."""
    import time
    from contextlib import ExitStack

    with ExitStack() as stack:
        outer = stack.enter_context(stage_run(TASK, "collect", 0, {}, tmp_path))
        with stage_run(TASK, "reference", 0, {}, tmp_path) as inner:
            pass
        time.sleep(0.02)
    assert outer.data["start_ms"] <= inner.data["start_ms"] and inner.data["end_ms"] < outer.data["end_ms"]
    (first, second) = pending_records(tmp_path)
    _log_record(first, tmp_path)
    run_id = _log_record(second, tmp_path)
    parent = store.get_run(run_id).data.tags["mlflow.parentRunId"]
    assert store.get_run(parent).info.end_time == outer.data["end_ms"]
    store.update_run(parent, status="RUNNING")  # as a crash right after the stage run's end left it
    log_pending(tmp_path)
    assert store.get_run(parent).info.status == "FINISHED" and pending_records(tmp_path) == []


def test_a_sweep_trial_keeps_its_outcome_and_its_run_ends_when_logging_fails(
    store: MlflowClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A pruned trial whose records cannot be logged (here a lock that is a folder) stays pruned, its run KILLED,
    one warning line; the records wait."""
    import optuna

    from adaptdiffuser.tooling.optuna_sweep import end_trial_run

    experiment_id = store.create_experiment(TASK)
    trial_run = store.create_run(experiment_id, tags={"sweep": "s"}).info.run_id
    trial_dir = tmp_path / "sweeps" / "s" / "trial_0"
    monkeypatch.setenv(PARENT_RUN_ENV, trial_run)
    with stage_run(TASK, "generate", 1, {}, trial_dir):
        pass
    (trial_dir / PENDING / ".lock").mkdir()
    with pytest.raises(optuna.TrialPruned, match="median"):
        try:
            raise optuna.TrialPruned("below the running median")
        finally:
            end_trial_run(store, trial_run, "KILLED", trial_dir, tmp_path)
    assert store.get_run(trial_run).info.status == "KILLED" and len(pending_records(trial_dir)) == 1
    (warning,) = capsys.readouterr().err.strip().splitlines()
    assert warning.startswith(f"warning: {trial_dir}: run records not logged") and "IsADirectoryError" in warning


def test_the_mlflow_log_command_takes_paths_logs_sweep_trials_and_exits_2_on_a_bad_record(
    store: MlflowClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`adaptdiffuser mlflow-log` with no path logs the project's records and those its sweep trials left (to the
    project's store, not a store in the trial's folder); given a pending folder, that one; a bad record: exit 2."""
    from typer.testing import CliRunner

    from adaptdiffuser.cli import app

    monkeypatch.delenv("MLFLOW_TRACKING_URI")  # the project's own store, <project>/mlflow.db
    experiment_id = store.create_experiment(TASK)
    trial_run = store.create_run(experiment_id, tags={"sweep": "s"}).info.run_id
    trial_dir = tmp_path / "sweeps" / "s" / "trial_3"
    with monkeypatch.context() as env:
        env.setenv(PARENT_RUN_ENV, trial_run)
        with stage_run(TASK, "generate", 1, {}, trial_dir) as trial_stage:
            pass
    with stage_run(TASK, "collect", 0, {}, tmp_path) as bad:
        pass
    (tmp_path / PENDING / bad.id / "record.json").write_text("[]")
    monkeypatch.chdir(tmp_path)
    out = CliRunner().invoke(app, ["mlflow-log"])
    assert out.exit_code == 2 and f"{tmp_path}: {bad.id}: record.json is not a mapping" in out.output, out.output
    (run,) = store.search_runs([experiment_id], "tags.stage = 'generate'")
    assert run.data.tags["mlflow.parentRunId"] == trial_run and run.data.tags["record_id"] == trial_stage.id
    assert not (trial_dir / "mlflow.db").exists() and pending_records(trial_dir) == []

    elsewhere = tmp_path / "other"
    with stage_run(TASK, "reference", 0, {}, elsewhere):
        pass
    out = CliRunner().invoke(app, ["mlflow-log", str(elsewhere / PENDING)])
    uri = f"sqlite:///{elsewhere / 'mlflow.db'}"  # its own store, not the one logged to before
    assert out.exit_code == 0 and f"logged 1 stage run(s) to {uri} from {elsewhere}\n" in out.output, out.output
    assert pending_records(elsewhere) == [] and (elsewhere / "mlflow.db").is_file()
    assert CliRunner().invoke(app, ["mlflow-log", str(tmp_path / "absent")]).exit_code == 1
