"""A real ``mlflow server`` (sqlite backend, served artifacts, one worker, no job runner) on 127.0.0.1: the collect
and pretrain stages of the smoke profile log to it through ``MLFLOW_TRACKING_URI``, nested under one pipeline run;
the pretrained model is registered, loads back with ``mlflow.pytorch.load_model`` from its alias and plans as the
checkpoint does; the summarize step's evolution curve and ``best`` alias land there too. And the rule by which
stage runs, separate processes, find their pipeline's parent run."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import mlflow
import mlflow.pytorch
import pytest
import torch
import yaml
from mlflow.tracking import MlflowClient
from smoke_project import narrow

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import apply_profile, params_from_dict
from adaptdiffuser.layout import dataset_path, model_dir
from adaptdiffuser.stages.collect import run_collect
from adaptdiffuser.stages.common import file_digest
from adaptdiffuser.stages.pretrain import run_pretrain
from adaptdiffuser.stages.summarize import log_evolution
from adaptdiffuser.tooling.mlflow_logging import (
    EXPERIMENT_KIND,
    EXPERIMENT_KIND_TAG,
    PARENT_RUN_ENV,
    PIPELINE_RUN_ENV,
    PIPELINE_STAGE,
    log_pending,
    registered_model_name,
    stage_run,
)

REPO = Path(__file__).resolve().parents[1]
TASK = "maze2d-umaze"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """``mlflow server`` in lean mode (as the README runs it beside a pipeline); its URL once it answers."""
    home = tmp_path_factory.mktemp("server")
    port = _free_port()
    cmd = [
        *(sys.executable, "-m", "mlflow", "server"),
        *("--backend-store-uri", f"sqlite:///{home / 'mlflow.db'}"),
        *("--artifacts-destination", str(home / "artifacts")),
        *("--host", "127.0.0.1", "--port", str(port), "--workers", "1"),
    ]
    env = os.environ | {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    log = (home / "server.log").open("w")
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180
        while True:
            assert proc.poll() is None, f"mlflow server exited:\n{(home / 'server.log').read_text()}"
            try:
                with urllib.request.urlopen(f"{url}/health", timeout=2) as answer:
                    if answer.status == 200:
                        break
            except OSError:
                pass
            assert time.monotonic() < deadline, f"mlflow server did not answer:\n{(home / 'server.log').read_text()}"
            time.sleep(0.5)
        yield url
    finally:
        os.killpg(proc.pid, signal.SIGTERM)  # the server and the uvicorn worker it started (its own session)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        log.close()


def test_stages_log_to_a_tracking_server(server: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", server)
    for name in ("DVC_EXP_NAME", "DVC_ROOT", PIPELINE_RUN_ENV, PARENT_RUN_ENV):
        monkeypatch.delenv(name, raising=False)
    raw = yaml.safe_load(apply_profile("smoke", REPO / "profiles", tmp_path / "params.yaml").read_text())
    params = params_from_dict(narrow(raw, [TASK], unseen_tasks=[TASK], evolve=TASK))
    try:
        run_collect(params, TASK, tmp_path, progress=False)
        run_pretrain(params, TASK, tmp_path, torch.device("cpu"), progress=False)
        log_evolution(TASK, {"phase_0": {"score_mean": 12.5, "score_stderr": 1.0}}, tmp_path)
        log_pending(tmp_path)  # as the summarize stage does after its own runs

        client = MlflowClient(server)
        experiment = client.get_experiment_by_name(TASK)
        assert experiment.tags[EXPERIMENT_KIND_TAG] == EXPERIMENT_KIND
        assert experiment.artifact_location.startswith("mlflow-artifacts:")  # the server stores the artifacts
        runs = client.search_runs([experiment.experiment_id])
        (parent,) = [run for run in runs if run.data.tags["stage"] == PIPELINE_STAGE]
        stages = {run.data.tags["stage"]: run for run in runs if run is not parent}
        assert set(stages) == {"collect", "pretrain", "summarize"}  # one pipeline run, each stage once
        assert all(run.data.tags["mlflow.parentRunId"] == parent.info.run_id for run in stages.values())
        assert parent.info.status == "FINISHED" and parent.data.tags["params_digest"] != "none"
        assert parent.data.params["pretrain.steps"] == "20"  # params.yaml, for comparing pipelines

        pretrain = stages["pretrain"]
        (dataset,) = pretrain.inputs.dataset_inputs
        digest = file_digest(tmp_path / dataset_path(TASK))
        assert dataset.dataset.name == str(dataset_path(TASK)) and dataset.dataset.digest == digest[:32]
        assert {t.key: t.value for t in dataset.tags}["mlflow.data.context"] == "training"
        assert [m.step for m in client.get_metric_history(stages["summarize"].info.run_id, "score")] == [0]

        name = registered_model_name(TASK)
        assert set(client.get_registered_model(name).aliases) == {"phase0", "phase0-seed0", "best"}
        version = client.get_model_version_by_alias(name, "best")
        assert version.run_id == pretrain.info.run_id and version.tags["label"] == "phase0"
        loaded = mlflow.pytorch.load_model(f"models:/{name}@best")
        bundle = load_bundle(tmp_path / model_dir(TASK, 0, 0))
        x = torch.randn(2, bundle.ema.horizon, bundle.ema.transition_dim, generator=torch.Generator().manual_seed(0))
        t = torch.tensor([0, 5])
        with torch.no_grad():
            assert torch.equal(loaded.model(x, t), bundle.ema.model(x, t))
        assert loaded.horizon == bundle.ema.horizon and loaded.n_steps == bundle.ema.n_steps
    finally:
        mlflow.set_tracking_uri(None)


def test_stage_runs_find_their_pipeline_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The rule that groups stage runs (separate processes) under one parent: the git commit and params.yaml, else
    the DVC experiment, else a name of one's own; and an experiment the UI had marked GenAI becomes a training one."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    for name in ("DVC_EXP_NAME", "DVC_EXP_BASELINE_REV", "DVC_ROOT", PIPELINE_RUN_ENV, PARENT_RUN_ENV):
        monkeypatch.delenv(name, raising=False)
    client = MlflowClient(uri)
    params = tmp_path / "params.yaml"
    params.write_text("alpha: 1\n")

    def parent() -> str:
        with stage_run("t", "collect", 0, {}, tmp_path) as run:
            pass
        run_id = log_pending(tmp_path)[run.id]
        return client.get_run(run_id).data.tags["mlflow.parentRunId"]

    try:
        repro = parent()
        experiment = client.get_experiment_by_name("t")
        client.set_experiment_tag(experiment.experiment_id, EXPERIMENT_KIND_TAG, "genai_development_inferred")
        assert parent() == repro  # the next stage of the same `dvc repro`
        assert client.get_experiment_by_name("t").tags[EXPERIMENT_KIND_TAG] == EXPERIMENT_KIND
        assert client.get_run(repro).data.params == {"alpha": "1"} and client.get_run(repro).info.status == "FINISHED"
        params.write_text("alpha: 2\n")
        changed = parent()
        assert changed != repro
        monkeypatch.setenv("DVC_EXP_NAME", "alpha50")
        exp = parent()
        assert exp not in (repro, changed) and parent() == exp
        assert client.get_run(exp).info.run_name == "exp-alpha50"
        assert client.get_run(exp).data.tags["dvc_exp_name"] == "alpha50"
        monkeypatch.setenv(PIPELINE_RUN_ENV, "mine")
        assert client.get_run(parent()).info.run_name == "mine"
        runs = client.search_runs([experiment.experiment_id], f"tags.stage = '{PIPELINE_STAGE}'")
        assert len(runs) == 4
    finally:
        mlflow.set_tracking_uri(None)
