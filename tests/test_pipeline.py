"""End to end: the real DVC pipeline on the smoke profile in a temporary git repository, with real MLflow."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import mlflow
import networkx as nx
import pytest
from dvc.repo import Repo
from mlflow.tracking import MlflowClient

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import load_params
from adaptdiffuser.data.schema import read_trajectories
from adaptdiffuser.tracking import stage_run

REPO = Path(__file__).resolve().parents[1]
PROJECT_FILES = ["dvc.yaml", "params.yaml", "pipeline", "profiles", "src", ".dvcignore", ".gitignore"]
PHASE_STAGES = ("generate", "discriminate", "finetune", "evaluate", "evaluate-coin")
STAGES = [
    "collect",
    "reference",
    "pretrain",
    "evaluate-phase0",
    "evaluate-coin-phase0",
    *(f"{stage}@phase{k}" for k in (1, 2) for stage in PHASE_STAGES),
    "summarize",
    "report",
]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env['PATH']}"
    env.pop("MLFLOW_TRACKING_URI", None)
    env["DVC_NO_ANALYTICS"] = "1"
    return env


def _run(cmd: list[str], cwd: Path) -> str:
    out = subprocess.run(cmd, cwd=cwd, env=_env(), capture_output=True, text=True)
    assert out.returncode == 0, f"{' '.join(cmd)} failed:\n{out.stdout}\n{out.stderr}"
    return out.stdout + out.stderr


@pytest.fixture(scope="module")
def smoke_repo(tmp_path_factory) -> Path:
    """A temporary git + DVC repository holding the project on the smoke profile, after one `dvc repro`."""
    root = tmp_path_factory.mktemp("project")
    for name in PROJECT_FILES:
        src = REPO / name
        if src.is_dir():
            shutil.copytree(src, root / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            shutil.copy2(src, root / name)
    _run(["git", "init", "-q"], root)
    _run(["git", "config", "user.email", "test@example.com"], root)
    _run(["git", "config", "user.name", "test"], root)
    _run(["dvc", "init", "-q"], root)
    _run(["adaptdiffuser", "profile", "smoke"], root)
    _run(["git", "add", "-A"], root)
    _run(["git", "commit", "-qm", "smoke project"], root)
    _run(["dvc", "repro"], root)
    return root


@pytest.mark.e2e
def test_repro_produces_data_model_and_metrics(smoke_repo: Path) -> None:
    traj = read_trajectories(smoke_repo / "data/expert.parquet")
    assert len(traj) == 4000 and traj.metadata["source"] == "expert" and traj.metadata["env"] == "maze2d-umaze"

    bundle = load_bundle(smoke_repo / "models/phase0")
    assert bundle.config["phase"] == 0 and bundle.config["diffusion"]["horizon"] == 32

    summary = json.loads((smoke_repo / "metrics/summary.json").read_text())
    assert set(summary) == {"phase_0", "phase_1", "phase_2"}
    assert set(summary["phase_0"]) == {"navigation", "gold_coin"}
    for k in (0, 1, 2):
        coin = summary[f"phase_{k}"]["gold_coin"]
        assert {"pick_rate", "goal_rate", "both_rate", "collision_rate", "n_episodes"} <= set(coin)
        assert coin["n_episodes"] == 4 and 0.0 <= coin["both_rate"] <= coin["pick_rate"] <= 1.0
        nav = summary[f"phase_{k}"]["navigation"]
        assert set(nav) == {"score_mean", "score_stderr", "return_mean", "n_episodes", "success_rate"}
        assert nav["n_episodes"] == 3 and 0.0 <= nav["success_rate"] <= 1.0
        assert isinstance(nav["score_mean"], float) and isinstance(nav["n_episodes"], int)
    for k in (1, 2):
        disc = summary[f"phase_{k}"]["discriminator"]
        assert set(disc) == {"generated", "kept", "kept_fraction", "tracking_error_mean"}
        assert disc["generated"] == 16 and 1 <= disc["kept"] <= 16
        assert disc["kept_fraction"] == disc["kept"] / 16 and disc["tracking_error_mean"] > 0
        assert load_bundle(smoke_repo / f"models/phase{k}").config["previous"] == k - 1
        assert len(read_trajectories(smoke_repo / f"data/phase{k}/selected.parquet").episodes()) == disc["kept"]
        assert (smoke_repo / f"plots/discriminator/phase{k}.png").read_bytes()[:4] == b"\x89PNG"
    table = (smoke_repo / "metrics/score_by_phase.csv").read_text().splitlines()
    assert table[0].startswith("phase,score_mean,score_stderr") and [r.split(",")[0] for r in table[1:]] == [
        "0",
        "1",
        "2",
    ]
    assert (smoke_repo / "plots/report/score_by_phase.png").read_bytes()[:4] == b"\x89PNG"
    assert "score_by_phase.csv" in _run(["dvc", "plots", "show", "--json"], smoke_repo)

    ref = json.loads((smoke_repo / "metrics/reference.json").read_text())
    assert ref["r_max"] > ref["r_min"]
    pictures = sorted((smoke_repo / "plots/phase0").glob("*.png"))
    assert len(pictures) == 1 and pictures[0].read_bytes()[:4] == b"\x89PNG"
    assert (smoke_repo / "results/phase0/episodes.parquet").exists()

    shown = _run(["dvc", "metrics", "show", "--json"], smoke_repo)
    assert "score_mean" in shown


@pytest.mark.e2e
def test_mlflow_records_every_stage(smoke_repo: Path) -> None:
    client = MlflowClient(tracking_uri=f"sqlite:///{smoke_repo / 'mlflow.db'}")
    experiment = client.get_experiment_by_name("maze2d-umaze")
    assert experiment is not None
    assert experiment.artifact_location == (smoke_repo / "mlartifacts/maze2d-umaze").resolve().as_uri()
    runs = client.search_runs([experiment.experiment_id])
    by_stage = {(run.data.tags["stage"], run.data.tags["phase"]): run for run in runs}
    assert len(by_stage) == len(runs)
    assert set(by_stage) == {
        ("collect", "0"),
        ("reference", "0"),
        ("pretrain", "0"),
        ("evaluate", "0"),
        ("evaluate-coin", "0"),
    } | {(stage, str(k)) for k in (1, 2) for stage in PHASE_STAGES}
    for run in runs:
        assert run.info.status == "FINISHED" and len(run.data.tags["git_commit"]) == 40
    pretrain = by_stage["pretrain", "0"]
    assert pretrain.data.params["pretrain.steps"] == "20"
    losses = client.get_metric_history(pretrain.info.run_id, "train_loss")
    assert [m.step for m in losses] == [5, 10, 15, 20]
    artifacts = {a.path for a in client.list_artifacts(pretrain.info.run_id, "checkpoint")}
    assert {"checkpoint/model.pt", "checkpoint/ema.pt", "checkpoint/config.json"} <= artifacts
    for k in ("0", "1", "2"):
        evaluate = by_stage["evaluate", k]
        assert "navigation.score_mean" in evaluate.data.metrics
        assert [a.path for a in client.list_artifacts(evaluate.info.run_id, "plans")] == ["plans/plan_00.png"]
        coin = by_stage["evaluate-coin", k]
        assert coin.data.params["alpha"] == "10.0" and "gold_coin.both_rate" in coin.data.metrics
        assert [a.path for a in client.list_artifacts(coin.info.run_id, "gold_coin")] == ["gold_coin/coin_00.png"]
    # a fine-tuned model's run names exactly the data that trained it
    finetune = by_stage["finetune", "2"]
    for name in ("expert", "synthetic.phase1", "synthetic.phase2"):
        assert len(finetune.data.params[f"data.{name}.sha256"]) == 64
    assert finetune.data.params["model.path"] == "models/phase1"
    assert [m.step for m in client.get_metric_history(finetune.info.run_id, "train_loss")] == [5]
    assert by_stage["discriminate", "1"].data.metrics["discriminator.generated"] == 16


@pytest.mark.e2e
def test_second_repro_does_nothing_and_params_rerun_only_dependents(smoke_repo: Path) -> None:
    again = _run(["dvc", "repro"], smoke_repo)
    assert "Data and pipelines are up to date" in again

    params = smoke_repo / "params.yaml"
    original = params.read_text()
    try:
        params.write_text(original.replace("episodes: 3", "episodes: 2"))
        # a dry run lists the stages whose own deps or params changed (summarize follows if metrics change)
        evaluations = {"evaluate-phase0", "evaluate@phase1", "evaluate@phase2"}
        coin = {"evaluate-coin-phase0", "evaluate-coin@phase1", "evaluate-coin@phase2"}
        assert _dry_run(smoke_repo) == {"reference"} | evaluations
        params.write_text(original.replace("  sampler_steps: 4\n  replan_every", "  sampler_steps: 2\n  replan_every"))
        assert _dry_run(smoke_repo) == evaluations | coin
        # a phase-2 param reruns phase 2 only (and the summary that lists the phases)
        params.write_text(
            original.replace("phase2:\n    previous: 1", "phase2:\n    previous: 1\n    generate: {tasks: 8}")
        )
        assert _dry_run(smoke_repo) == {"generate@phase2", "discriminate@phase2", "finetune@phase2", "summarize"}
        # a generation default reruns generation in every phase; collect, reference and pretrain stay cached
        params.write_text(original.replace("  cell_spread: 0.4", "  cell_spread: 0.3"))
        assert _dry_run(smoke_repo) == {"generate@phase1", "generate@phase2"}
    finally:
        params.write_text(original)


def _dry_run(root: Path) -> set[str]:
    dry = _run(["dvc", "repro", "--dry"], root)
    return {stage for stage in STAGES if f"Running stage '{stage}'" in dry}


def test_phase_chain_in_dvc_yaml_matches_params_and_has_no_cycles() -> None:
    params = load_params(REPO / "params.yaml")
    with Repo(str(REPO)) as repo:
        graph = repo.index.graph  # edges point from a stage to the stages it depends on
        upstream = {stage.addressing: {dep.addressing for dep in graph.successors(stage)} for stage in graph.nodes}
        assert nx.is_directed_acyclic_graph(graph)
    expected = {"collect", "reference", "pretrain", "evaluate-phase0", "evaluate-coin-phase0", "summarize", "report"}
    expected |= {f"{stage}@{name}" for name in params.phase_names for stage in PHASE_STAGES}
    assert set(upstream) == expected
    for phase in params.phases:
        name = phase.name
        source = "pretrain" if phase.previous == 0 else f"finetune@phase{phase.previous}"
        assert upstream[f"generate@{name}"] == {source}
        assert upstream[f"discriminate@{name}"] == {f"generate@{name}"}
        assert upstream[f"finetune@{name}"] == {"collect", source, f"discriminate@{name}"}
        assert upstream[f"evaluate@{name}"] == {f"finetune@{name}", "reference"}
        assert upstream[f"evaluate-coin@{name}"] == {f"finetune@{name}", "reference"}
    assert upstream["summarize"] == {"evaluate-phase0", "evaluate-coin-phase0"} | {
        f"{stage}@{name}" for name in params.phase_names for stage in ("evaluate", "evaluate-coin", "discriminate")
    }
    assert upstream["report"] == {"summarize"}


@pytest.mark.e2e
def test_dvc_exp_run_alpha_reruns_only_what_alpha_affects(smoke_repo: Path, tmp_path: Path) -> None:
    repo = tmp_path / "exp"
    shutil.copytree(smoke_repo, repo)
    _run(["git", "add", "-A"], repo)
    _run(["git", "commit", "-qm", "baseline run"], repo)
    out = _run(["dvc", "exp", "run", "-n", "alpha50", "-S", "alpha=50"], repo)
    ran = {stage for stage in STAGES if f"Running stage '{stage}'" in out}
    # alpha guides coin tasks in generation and the coin evaluation; everything downstream of them follows
    assert {"collect", "reference", "pretrain", "evaluate-phase0"}.isdisjoint(ran)
    assert {"generate@phase1", "generate@phase2", "evaluate-coin-phase0", "evaluate-coin@phase2"} <= ran
    shown = json.loads(_run(["dvc", "exp", "show", "--json"], repo))
    assert "alpha50" in json.dumps(shown) and "both_rate" in json.dumps(shown)


@pytest.mark.e2e
def test_bad_params_stop_the_stage_before_work(smoke_repo: Path, tmp_path: Path) -> None:
    bad = tmp_path / "params.yaml"
    bad.write_text((smoke_repo / "params.yaml").read_text().replace("maze: umaze", "maze: spiral"))
    out = subprocess.run(
        [sys.executable, "pipeline/collect.py", "--params", str(bad)],
        cwd=smoke_repo,
        env=_env(),
        capture_output=True,
        text=True,
    )
    assert out.returncode == 2
    assert "env.maze" in out.stderr and "spiral" in out.stderr


def test_failed_stage_marks_mlflow_run_failed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    with pytest.raises(RuntimeError, match="boom"), stage_run("maze2d-test", "pretrain", 0, {"a": {"b": 1}}, tmp_path):
        raise RuntimeError("boom")
    client = MlflowClient(tracking_uri=uri)
    experiment = client.get_experiment_by_name("maze2d-test")
    (run,) = client.search_runs([experiment.experiment_id])
    assert run.info.status == "FAILED"
    assert run.data.params == {"a.b": "1"} and run.data.tags["stage"] == "pretrain"
    mlflow.set_tracking_uri(None)
