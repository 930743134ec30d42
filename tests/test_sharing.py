"""Sharing and running many experiments, with the real tools on the smoke project: a DVC remote that a fresh clone
pulls a finished run from, and the DVC experiment queue running two experiments at once (one of them the sweep's
best trial) with MLflow recording into the repository's own store."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient
from smoke_project import run_queue, run_tool

MAZE = "maze2d-umaze"
PHASE0_STAGES = ("collect", "reference", "pretrain", "evaluate-phase0")


def _committed_copy(smoke_repo: Path, dest: Path) -> Path:
    """A copy of the finished smoke run with its lock, params and metrics committed, as a user would share it."""
    shutil.copytree(smoke_repo, dest, symlinks=True)
    run_tool(["git", "add", "-A"], dest)
    run_tool(["git", "commit", "-qm", "smoke run"], dest)
    return dest


def _metrics(root: Path) -> dict:
    return json.loads(run_tool(["dvc", "metrics", "show", "--json"], root))[""]["data"]


@pytest.mark.e2e
def test_a_run_pushed_to_a_shared_remote_is_pulled_into_a_fresh_clone_without_retraining(
    smoke_repo: Path, tmp_path: Path
) -> None:
    origin = _committed_copy(smoke_repo, tmp_path / "origin")
    remote = tmp_path / "remote"
    run_tool(["dvc", "remote", "add", "-d", "shared", str(remote)], origin)
    run_tool(["git", "commit", "-qam", "shared remote"], origin)
    run_tool(["dvc", "push"], origin)

    clone = tmp_path / "clone"
    run_tool(["git", "clone", "-q", str(origin), str(clone)], tmp_path)
    model = Path(f"models/{MAZE}/phase2/seed0")
    assert not (clone / model).exists()  # only git's files so far
    run_tool(["dvc", "pull"], clone)
    assert "Data and pipelines are up to date" in run_tool(["dvc", "repro"], clone)  # nothing retrained
    assert _metrics(clone) == _metrics(origin)
    for path in (origin / model).rglob("*"):
        if path.is_file():
            assert (clone / model / path.relative_to(origin / model)).read_bytes() == path.read_bytes()


@pytest.mark.e2e
def test_the_queue_runs_two_experiments_at_once_one_of_them_the_sweeps_best_trial(
    smoke_repo: Path, tmp_path: Path
) -> None:
    repo = _committed_copy(smoke_repo, tmp_path / "exp")
    # the queue is what this test is about: one phase (the smoke project runs two), whose trial scores it (4 stages)
    # rather than its gain over the control (6); no stage reads `sweep`, and dropping phase 2 reruns no other phase
    run_tool(["adaptdiffuser", "set", "sweep.objective=score", "phases={phase1: {previous: 0}}"], repo)
    run_tool(["git", "commit", "-qam", "one phase, swept on the score"], repo)
    swept = run_tool(["adaptdiffuser", "sweep", "--trials", "1", "--workers", "1", "--dvc-exp", "queue"], repo)
    (best,) = re.findall(r"queued as DVC experiment (\S+):", swept)
    assert best == "adaptdiffuser-best-trial0"
    run_tool(["dvc", "exp", "run", "--queue", "-n", "alpha30", "-S", "alpha=30"], repo)

    status = run_queue(repo)
    assert status.count("Success") == 2, status

    # `dvc exp show` compares both with the baseline: their params and the summary's scores
    shown = json.dumps(json.loads(run_tool(["dvc", "exp", "show", "--json"], repo)))
    assert '"alpha30"' in shown and f'"{best}"' in shown and "both_rate" in shown
    # alpha guides generation and the coin evaluation only: the queued run reused phase 0 from the cache
    log = run_tool(["dvc", "queue", "logs", "alpha30"], repo)
    ran = set(re.findall(r"Running stage '([^']+)'", log))
    assert "generate@phase1" in ran and f"evaluate-unseen-phase0@{MAZE}" in ran
    assert ran.isdisjoint({f"{stage}@{MAZE}" for stage in PHASE0_STAGES})

    # the runs executed in DVC's temporary copies and were recorded in the repository's own MLflow store
    client = MlflowClient(f"sqlite:///{repo / 'mlflow.db'}")
    experiment = client.get_experiment_by_name(MAZE)
    for name in ("alpha30", best):  # what alpha changes directly always reruns; what follows, when its inputs change
        runs = client.search_runs([experiment.experiment_id], filter_string=f"tags.dvc_exp_name = '{name}'")
        assert {run.data.tags["stage"] for run in runs} >= {"generate", "evaluate-unseen"}, name
    (parent,) = client.search_runs([experiment.experiment_id], filter_string="tags.stage = 'sweep'")
    assert parent.data.tags["dvc_experiment"] == best
