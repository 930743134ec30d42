"""End to end: the real DVC pipeline on the smoke profile in a temporary git repository, with real MLflow."""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import mlflow
import networkx as nx
import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml
from deps_trace import check, load_traces, missing_message
from dvc.repo import Repo
from mlflow.tracking import MlflowClient
from smoke_project import run_tool as _run
from smoke_project import tool_env as _env
from smoke_project import traces_dir

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import apply_profile, load_params, stage_names
from adaptdiffuser.data.schema import read_trajectories
from adaptdiffuser.tooling.mlflow_logging import log_pending, stage_run

REPO = Path(__file__).resolve().parents[1]
PHASE_STAGES = ("generate", "discriminate", "finetune", "evaluate", "control", "evaluate-control")
PHASE_STAGES += ("evaluate-unseen", "evaluate-unseen-control")
MAZE, HOPPER, KUKA = "maze2d-umaze", "hopper-medium", "kuka-stacking"
PHASE0_STAGES = ("collect", "reference", "pretrain", "evaluate-phase0")
STAGES = [
    *(f"code@{task}" for task in (MAZE, HOPPER, KUKA)),
    *(f"{stage}@{task}" for task in (MAZE, HOPPER, KUKA) for stage in PHASE0_STAGES),
    f"evaluate-unseen-phase0@{MAZE}",
    f"evaluate-unseen-phase0@{KUKA}",
    *(f"{stage}@phase{k}" for k in (1, 2) for stage in PHASE_STAGES),
    "summarize",
    "report",
]


@pytest.mark.e2e
def test_repro_produces_data_model_and_metrics(smoke_repo: Path) -> None:
    traj = read_trajectories(smoke_repo / f"data/{MAZE}/dataset.parquet")
    assert len(traj) == 4000 and traj.metadata["source"] == "expert" and traj.metadata["env"] == MAZE

    bundle = load_bundle(smoke_repo / f"models/{MAZE}/phase0/seed0")
    assert bundle.config["phase"] == 0 and bundle.config["diffusion"]["horizon"] == 32
    assert bundle.config["conditioning"] == "start_goal" and bundle.normalizer.kind == "minmax"

    summary = json.loads((smoke_repo / "metrics/summary.json").read_text())
    assert set(summary) == {MAZE, HOPPER, KUKA}
    maze = summary[MAZE]
    assert set(maze) == {"reference", "unseen_task", "phase_0", "phase_1", "phase_2"}
    assert maze["unseen_task"] == "gold_coin" and {"d4rl_r_min", "d4rl_r_max"} <= set(maze["reference"])
    for k in (0, 1, 2):
        entry = maze[f"phase_{k}"]
        for coin in [entry["gold_coin"]] + ([entry["control"]["gold_coin"]] if k else []):  # phase and control
            assert {"pick_rate", "goal_rate", "both_rate", "collision_rate", "n_episodes"} <= set(coin)
            assert coin["n_episodes"] == 4 and 0.0 <= coin["both_rate"] <= coin["pick_rate"] <= 1.0
        assert {"score_mean", "score_stderr", "return_mean", "n_episodes", "success_rate"} <= set(entry)
        assert entry["n_episodes"] == 3 and 0.0 <= entry["success_rate"] <= 1.0
        assert isinstance(entry["score_mean"], float) and isinstance(entry["n_episodes"], int)
    for k in (1, 2):
        disc = maze[f"phase_{k}"]["discriminator"]
        assert set(disc) == {"generated", "tracked", "kept", "kept_fraction", "tracking_error_mean", "return_mean_kept"}
        assert disc["generated"] == 16 and 1 <= disc["kept"] <= disc["tracked"] <= 16 and disc["return_mean_kept"] >= 0
        assert disc["kept_fraction"] == disc["kept"] / 16 and disc["tracking_error_mean"] > 0
        entry, control = maze[f"phase_{k}"], maze[f"phase_{k}"]["control"]
        assert control["n_episodes"] == 3 and "gain_mean" not in control
        # the gain is paired over the same episodes: its mean is the difference of the two means
        assert entry["gain_mean"] == pytest.approx(entry["score_mean"] - control["score_mean"])
        assert entry["gain_stderr"] >= 0.0 and entry["stderr_over"] == "episodes" and entry["n_seeds"] == 1
        assert entry["per_seed"]["0"]["gain_mean"] == entry["gain_mean"]
        control_model = load_bundle(smoke_repo / f"models/{MAZE}/phase{k}-control/seed0")
        assert control_model.config["control"] is True and control_model.config["data"]["synthetic"] == {}
        assert load_bundle(smoke_repo / f"models/{MAZE}/phase{k}/seed0").config["previous"] == k - 1
        selected = read_trajectories(smoke_repo / f"data/{MAZE}/phase{k}/selected/seed0.parquet")
        assert len(selected.episodes()) == disc["kept"]
        assert (smoke_repo / f"plots/{MAZE}/discriminator/phase{k}/seed0.png").read_bytes()[:4] == b"\x89PNG"
    table = (smoke_repo / f"metrics/report/{MAZE}/score_by_phase.csv").read_text().splitlines()
    assert table[0].startswith("phase,score_mean,score_stderr,score_ci_low,score_ci_high,control_score_mean")
    assert [r.split(",")[0] for r in table[1:]] == ["0", "1", "2"]
    assert (smoke_repo / f"plots/report/{MAZE}/score_by_phase.png").read_bytes()[:4] == b"\x89PNG"
    assert f"{MAZE}/score_by_phase.csv" in _run(["dvc", "plots", "show", "--json"], smoke_repo)

    ref = json.loads((smoke_repo / f"metrics/tasks/{MAZE}/reference.json").read_text())
    assert ref["r_max"] > ref["r_min"]
    pictures = sorted((smoke_repo / f"plots/{MAZE}/phase0/seed0").glob("*.png"))
    assert len(pictures) == 1 and pictures[0].read_bytes()[:4] == b"\x89PNG"
    assert (smoke_repo / f"results/{MAZE}/phase0/seed0/episodes.parquet").exists()

    shown = _run(["dvc", "metrics", "show", "--json"], smoke_repo)
    assert "score_mean" in shown


@pytest.mark.e2e
def test_dvc_yaml_lists_every_module_and_file_each_stage_uses(smoke_repo: Path) -> None:
    """The repro traced every stage (modules loaded, files read): each traced path is under one of its deps."""
    traces = load_traces(traces_dir(smoke_repo))  # not empty: every stage loaded the CLI and read something
    assert all("src/adaptdiffuser/cli.py" in trace.modules and trace.reads for trace in traces.values())
    message = missing_message(check(smoke_repo, traces_dir(smoke_repo)))  # raises if a stage left no trace
    assert not message, f"dvc.yaml misses deps that stages use:\n{message}"


@pytest.mark.e2e
def test_repro_runs_the_locomotion_baseline(smoke_repo: Path) -> None:
    """hopper-medium: behaviour policy, its dataset with full states, Gaussian-normalized start-conditioned model,
    value function, value-guided evaluation under D4RL's score, and the dataset's own score in the summary."""
    traj = read_trajectories(smoke_repo / f"data/{HOPPER}/dataset.parquet")
    assert len(traj) == 2000 and traj.sim_state is not None and traj.metadata["state_dim"] == 12
    assert (smoke_repo / f"models/{HOPPER}/collect/medium.zip").exists()
    bundle = load_bundle(smoke_repo / f"models/{HOPPER}/phase0/seed0")
    assert bundle.config["conditioning"] == "start" and bundle.normalizer.kind == "gaussian"
    assert bundle.config["diffusion"]["horizon"] == 16 and bundle.config["diffusion"]["action_weight"] == 10.0
    assert (smoke_repo / f"models/{HOPPER}/phase0/seed0/value/value.pt").exists()
    ref = json.loads((smoke_repo / f"metrics/tasks/{HOPPER}/reference.json").read_text())
    assert (ref["r_min"], ref["r_max"]) == (-20.272305, 3234.3)
    assert {"random_score_mean", "behaviour_score_mean", "dataset"} <= set(ref)
    summary = json.loads((smoke_repo / "metrics/summary.json").read_text())[HOPPER]
    assert set(summary) == {"reference", "dataset", "phase_0"}
    assert summary["dataset"]["score_mean"] == ref["dataset"]["score_mean"]
    assert summary["reference"] == {"r_min": -20.272305, "r_max": 3234.3}  # D4RL's are ours: no second set
    phase0 = summary["phase_0"]
    assert phase0["n_episodes"] == 2 and 1 <= phase0["length_mean"] <= 40
    assert 0.0 <= phase0["terminated_rate"] <= 1.0
    episodes = (smoke_repo / f"results/{HOPPER}/phase0/seed0/episodes.parquet").exists()
    assert episodes and (smoke_repo / f"plots/{HOPPER}/phase0/seed0/plan_00.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.e2e
def test_repro_runs_the_kuka_baseline(smoke_repo: Path) -> None:
    """kuka-stacking: state-only demonstrations, a start-conditioned min/max model, stacking scored against the
    demonstrator and random joints, pick-and-place for both setups beside it, and a picture of the final scene."""
    traj = read_trajectories(smoke_repo / f"data/{KUKA}/dataset.parquet")
    assert traj.metadata["act_dim"] == 0 and traj.observation.shape[1] == 39 and len(traj.episodes()) == 2
    demonstrator = json.loads((smoke_repo / f"models/{KUKA}/collect/demonstrator.json").read_text())
    assert demonstrator["episodes"] == 2 and 0.0 <= demonstrator["success_rate"] <= 1.0
    bundle = load_bundle(smoke_repo / f"models/{KUKA}/phase0/seed0")
    assert bundle.config["conditioning"] == "start" and bundle.normalizer.kind == "minmax"
    assert bundle.config["act_dim"] == 0
    ref = json.loads((smoke_repo / f"metrics/tasks/{KUKA}/reference.json").read_text())
    assert (ref["r_min"], ref["r_max"]) == (0.0, 3.0)
    assert {"demonstrator_score_mean", "random_score_mean"} <= set(ref)
    phase0 = json.loads((smoke_repo / "metrics/summary.json").read_text())[KUKA]["phase_0"]
    assert phase0["n_episodes"] == 2 and 0.0 <= phase0["score_mean"] <= 100.0
    place = phase0["pick_place"]  # the unseen task, evaluated by its own stage
    assert place["n_episodes"] == 4 and 0.0 <= place["score_mean"] <= 100.0
    setups = [place[f"setup{setup}_score_mean"] for setup in (1, 2)]
    assert all(0.0 <= score <= 100.0 for score in setups) and place["score_mean"] == pytest.approx(np.mean(setups))
    gains = _run(["adaptdiffuser", "gains"], smoke_repo)  # pick-and-place listed under the scores
    assert f"| {KUKA} | 0 | pick_place | score | {place['score_mean']:.1f} ± " in gains
    assert f"| {KUKA} | 0 | pick_place | setup2_score | {place['setup2_score_mean']:.1f} ± " in gains  # per setup
    results = pq.read_table(smoke_repo / f"results/{KUKA}/phase0/seed0/episodes.parquet").to_pydict()
    assert results["length"] == [2 * 15, 2 * 15]  # two open-loop plans of 16 states (15 steps each)
    assert (smoke_repo / f"plots/{KUKA}/phase0/seed0/plan_00.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.e2e
def test_mlflow_records_every_stage(smoke_repo: Path) -> None:
    client = MlflowClient(tracking_uri=f"sqlite:///{smoke_repo / 'mlflow.db'}")
    experiment = client.get_experiment_by_name(MAZE)
    assert experiment is not None
    assert experiment.artifact_location == (smoke_repo / f"mlartifacts/{MAZE}").resolve().as_uri()
    assert experiment.tags["mlflow.experimentKind"] == "custom_model_development"  # the UI opens on the runs
    runs = client.search_runs([experiment.experiment_id])
    (parent,) = [run for run in runs if run.data.tags["stage"] == "pipeline"]  # one `dvc repro`, one pipeline run
    runs = [run for run in runs if run is not parent]
    assert all(run.data.tags["mlflow.parentRunId"] == parent.info.run_id for run in runs)
    assert parent.info.status == "FINISHED" and parent.data.tags["git_commit"] == runs[0].data.tags["git_commit"]
    by_stage = {(run.data.tags["stage"], run.data.tags["phase"]): run for run in runs}
    assert len(by_stage) == len(runs)
    assert set(by_stage) == {
        ("collect", "0"),
        ("reference", "0"),
        ("pretrain", "0"),
        ("evaluate", "0"),
        ("evaluate-unseen", "0"),
        ("summarize", "all"),
    } | {(stage, str(k)) for k in (1, 2) for stage in PHASE_STAGES}
    for run in runs:
        assert run.info.status == "FINISHED" and len(run.data.tags["git_commit"]) == 40
        if run.data.tags["stage"] not in ("collect", "reference", "summarize"):  # one run per training seed
            assert run.data.tags["seed"] == "0" and run.info.run_name.endswith("-seed0")
    pretrain = by_stage["pretrain", "0"]
    assert pretrain.data.params["pretrain.steps"] == "20"
    losses = client.get_metric_history(pretrain.info.run_id, "train_loss")
    assert [m.step for m in losses] == [5, 10, 15, 20]
    artifacts = {a.path for a in client.list_artifacts(pretrain.info.run_id, "checkpoint")}
    assert {"checkpoint/model.pt", "checkpoint/ema.pt", "checkpoint/config.json"} <= artifacts
    for k in ("0", "1", "2"):
        evaluate = by_stage["evaluate", k]
        assert "score_mean" in evaluate.data.metrics
        assert [a.path for a in client.list_artifacts(evaluate.info.run_id, "plans")] == ["plans/plan_00.png"]
        for stage in ("evaluate-unseen", "evaluate-unseen-control") if k != "0" else ("evaluate-unseen",):
            coin = by_stage[stage, k]
            assert coin.data.params["alpha"] == "10.0" and "gold_coin.both_rate" in coin.data.metrics
            assert [a.path for a in client.list_artifacts(coin.info.run_id, "gold_coin")] == ["gold_coin/coin_00.png"]
    # a fine-tuned model's run names exactly the data that trained it
    finetune = by_stage["finetune", "2"]
    for name in ("expert", "synthetic.phase1", "synthetic.phase2"):
        assert len(finetune.data.params[f"data.{name}.sha256"]) == 64
    assert finetune.data.params["model.path"] == f"models/{MAZE}/phase1/seed0"
    assert [m.step for m in client.get_metric_history(finetune.info.run_id, "train_loss")] == [5]
    # the control of phase 2: the same start model, steps and seed, expert data only
    control = by_stage["control", "2"]
    assert control.data.params["model.path"] == f"models/{MAZE}/phase1/seed0"
    assert "data.synthetic.phase1.sha256" not in control.data.params
    for key in ("train.steps", "train.seed", "data.expert.sha256"):
        assert control.data.params[key] == finetune.data.params[key]
    assert [m.step for m in client.get_metric_history(control.info.run_id, "train_loss")] == [5]
    assert {"gain_mean", "gain_stderr", "score_mean"} <= set(by_stage["evaluate-control", "2"].data.metrics)
    assert by_stage["discriminate", "1"].data.metrics["discriminator.generated"] == 16
    # what each training run trained on, as MLflow dataset inputs (name, digest and context)
    contexts = {
        d.dataset.name: {t.key: t.value for t in d.tags}["mlflow.data.context"] for d in finetune.inputs.dataset_inputs
    }
    assert contexts == {
        f"data/{MAZE}/dataset.parquet": "training",
        f"data/{MAZE}/phase1/selected/seed0.parquet": "synthetic-phase1",
        f"data/{MAZE}/phase2/selected/seed0.parquet": "synthetic-phase2",
    }
    assert [d.dataset.name for d in pretrain.inputs.dataset_inputs] == [f"data/{MAZE}/dataset.parquet"]
    assert [d.dataset.name for d in control.inputs.dataset_inputs] == [f"data/{MAZE}/dataset.parquet"]
    # the evolution curve (step = phase) and the registered models, `best` on the phase with the highest score
    summary = json.loads((smoke_repo / "metrics/summary.json").read_text())[MAZE]
    curve = by_stage["summarize", "all"]
    scores = [m.value for m in client.get_metric_history(curve.info.run_id, "score")]
    assert scores == [summary[f"phase_{k}"]["score_mean"] for k in (0, 1, 2)]
    assert [m.step for m in client.get_metric_history(curve.info.run_id, "gain")] == [1, 2]
    model = client.get_registered_model(f"adaptdiffuser-{MAZE}")
    labels = {"phase0", "phase1", "phase2", "phase1-control", "phase2-control"}
    assert set(model.aliases) == labels | {f"{label}-seed0" for label in labels} | {"best"}
    best = client.get_model_version_by_alias(model.name, "best")
    assert best.tags["label"] == f"phase{curve.data.tags['best_phase']}" == f"phase{scores.index(max(scores))}"
    # the locomotion task has its own experiment, with the value function's training beside pretraining
    hopper = client.get_experiment_by_name(HOPPER)
    stages = {run.data.tags["stage"] for run in client.search_runs([hopper.experiment_id])}
    assert stages == {"pipeline", "collect", "reference", "pretrain", "value", "evaluate", "summarize"}
    # `adaptdiffuser times`: every stage run of this pipeline run, every task, with its duration
    lines = _run(["adaptdiffuser", "times"], smoke_repo).splitlines()
    assert f"{MAZE}  pretrain-phase0-seed0  FINISHED" in "\n".join(lines) and f"{HOPPER}  value" in "\n".join(lines)
    every = sum(
        len(client.search_runs([e.experiment_id])) - 1 for e in client.search_experiments() if e.name != "Default"
    )
    assert len(lines) == every + 1 and lines[-1].endswith(f"in all ({every} stage runs)")


@pytest.mark.e2e
def test_second_repro_does_nothing_and_params_rerun_only_dependents(smoke_repo: Path) -> None:
    again = _run(["dvc", "repro"], smoke_repo)
    assert "Data and pipelines are up to date" in again

    params = smoke_repo / "params.yaml"
    original = params.read_text()
    raw = yaml.safe_load(original)

    def dry_run_with(change) -> set[str]:
        edited = copy.deepcopy(raw)
        change(edited)
        params.write_text(yaml.safe_dump(edited, sort_keys=False))
        return _dry_run(smoke_repo)

    evaluations = {f"evaluate-phase0@{MAZE}", "evaluate@phase1", "evaluate@phase2"}
    evaluations |= {"evaluate-control@phase1", "evaluate-control@phase2"}
    coin = {f"evaluate-unseen-phase0@{task}" for task in (MAZE, KUKA)}
    coin |= {f"{stage}@phase{k}" for stage in ("evaluate-unseen", "evaluate-unseen-control") for k in (1, 2)}
    try:
        # a generic evaluation key: every task's reference and evaluations (summarize follows when metrics change)
        ran = dry_run_with(lambda p: p["evaluate"].update(episodes=2))
        others = {f"{stage}@{task}" for task in (HOPPER, KUKA) for stage in ("reference", "evaluate-phase0")}
        assert ran == {f"reference@{MAZE}", *others, *evaluations}
        assert dry_run_with(lambda p: p["planner"].update(sampler_steps=2)) == (
            evaluations | coin | {f"reference@{MAZE}", *others}
        )
        # one task's own entry reruns that task's stages only
        ran = dry_run_with(lambda p: p["task"][HOPPER]["guide"].update(n_samples=3))
        assert ran == {f"{stage}@{HOPPER}" for stage in PHASE0_STAGES}
        # a phase-2 param reruns phase 2 only (and the summary that lists the phases)
        ran = dry_run_with(lambda p: p["phases"]["phase2"].update(generate={"tasks": 8}))
        assert ran == {"generate@phase2", "discriminate@phase2", "finetune@phase2", "control@phase2", "summarize"}
        # a generation default reruns generation in every phase; collect, reference and pretrain stay cached
        ran = dry_run_with(lambda p: p["evolution"]["generate"].update(batch_size=4))  # smoke: 8
        assert ran == {"generate@phase1", "generate@phase2"}
        # so does the recipe (Maze2D's rollouts): phase 0 and phase 1's control stay cached, so recipes share them
        ran = dry_run_with(lambda p: p["evolution"]["generate"].update(recipe="rollouts", replan_every=8))
        assert ran == {"generate@phase1", "generate@phase2"}
    finally:
        params.write_text(original)


@pytest.mark.e2e
@pytest.mark.parametrize("family", ["maze2d", "locomotion", "kuka"])
def test_editing_one_family_leaves_the_other_families_stages_up_to_date(smoke_repo: Path, family: str) -> None:
    """A comment appended to a file of one family changes the code fingerprint stages of that family's task entries
    and nothing else: `dvc status` names no stage of another family's task (the smoke profile runs one task of each
    family). Its ``params.py`` is the exception the summary shares: summarize loads every family's task model."""
    entries = yaml.safe_load((smoke_repo / "params.yaml").read_text())["task"]
    fingerprints = {f"code@{name}" for name, entry in entries.items() if entry["family"] == family}
    folder = smoke_repo / f"src/adaptdiffuser/families/{family}"
    for name, expected in (("family.py", fingerprints), ("params.py", fingerprints | {"summarize"})):
        original = (folder / name).read_text()
        try:
            (folder / name).write_text(original + "# an edit that changes no behaviour\n")
            status = json.loads(_run(["dvc", "status", "--json"], smoke_repo))
        finally:
            (folder / name).write_text(original)
        assert set(status) == expected, (name, status)
    assert json.loads(_run(["dvc", "status", "--json"], smoke_repo)) == {}


def _dry_run(root: Path) -> set[str]:
    dry = _run(["dvc", "repro", "--dry"], root)
    return {stage for stage in STAGES if f"Running stage '{stage}'" in dry}


def test_phase_chain_in_dvc_yaml_matches_params_and_has_no_cycles(tmp_path: Path) -> None:
    """On the smoke profile (every family): every stage of stage_names, wired task by task."""
    for name in ["dvc.yaml", "profiles"]:
        src = REPO / name
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, tmp_path / name)
    apply_profile("smoke", tmp_path / "profiles", tmp_path / "params.yaml")
    params = load_params(tmp_path / "params.yaml")
    with Repo.init(str(tmp_path), no_scm=True) as repo:
        graph = repo.index.graph  # edges point from a stage to the stages it depends on
        upstream = {stage.name: {dep.name for dep in graph.successors(stage)} for stage in graph.nodes}
        assert nx.is_directed_acyclic_graph(graph)
    assert set(upstream) == set(stage_names(params))
    # STAGES, and a code fingerprint stage for each other task entry of the profile (tests use them outside DVC)
    assert set(upstream) - set(STAGES) == {f"code@{task}" for task in params.task if task not in (MAZE, HOPPER, KUKA)}
    for task in (MAZE, HOPPER, KUKA):  # every stage of a task depends on its task's code fingerprint
        code = f"code@{task}"
        assert upstream[code] == set()
        assert upstream[f"collect@{task}"] == {code}
        assert upstream[f"reference@{task}"] == {f"collect@{task}", code}
        assert upstream[f"pretrain@{task}"] == {f"collect@{task}", code}
        assert upstream[f"evaluate-phase0@{task}"] == {f"pretrain@{task}", f"reference@{task}", code}
    for task in (MAZE, KUKA):  # the families with an unseen task
        code = f"code@{task}"
        assert upstream[f"evaluate-unseen-phase0@{task}"] == {f"pretrain@{task}", f"reference@{task}", code}
    code = f"code@{MAZE}"
    for phase in params.phases:
        name = phase.name
        source = f"pretrain@{MAZE}" if phase.previous == 0 else f"finetune@phase{phase.previous}"
        assert upstream[f"generate@{name}"] == {source, f"collect@{MAZE}", code}
        assert upstream[f"discriminate@{name}"] == {f"generate@{name}", f"collect@{MAZE}", code}
        assert upstream[f"finetune@{name}"] == {f"collect@{MAZE}", source, f"discriminate@{name}", code}
        assert upstream[f"evaluate@{name}"] == {f"finetune@{name}", f"reference@{MAZE}", code}
        assert upstream[f"evaluate-unseen@{name}"] == {f"finetune@{name}", f"reference@{MAZE}", code}
        assert upstream[f"evaluate-unseen-control@{name}"] == {f"control@{name}", f"reference@{MAZE}", code}
        assert upstream[f"control@{name}"] == {f"collect@{MAZE}", source, code}
        assert upstream[f"evaluate-control@{name}"] == {
            f"control@{name}",
            f"evaluate@{name}",
            f"reference@{MAZE}",
            code,
        }
    assert upstream["summarize"] == {
        f"{stage}@{task}" for task in (MAZE, HOPPER, KUKA) for stage in ("reference", "evaluate-phase0")
    } | {f"evaluate-unseen-phase0@{MAZE}", f"evaluate-unseen-phase0@{KUKA}"} | {
        f"{stage}@{name}"
        for name in params.phase_names
        for stage in ("evaluate", "evaluate-control", "evaluate-unseen", "evaluate-unseen-control", "discriminate")
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
    assert {f"{stage}@{task}" for task in (MAZE, HOPPER, KUKA) for stage in PHASE0_STAGES}.isdisjoint(ran)
    assert {"generate@phase1", "generate@phase2", f"evaluate-unseen-phase0@{MAZE}", "evaluate-unseen@phase2"} <= ran
    shown = json.loads(_run(["dvc", "exp", "show", "--json"], repo))
    assert "alpha50" in json.dumps(shown) and "both_rate" in json.dumps(shown)


@pytest.mark.e2e
def test_bad_params_stop_the_stage_before_work(smoke_repo: Path, tmp_path: Path) -> None:
    bad = tmp_path / "params.yaml"
    bad.write_text((smoke_repo / "params.yaml").read_text().replace("maze: umaze", "maze: spiral"))
    out = subprocess.run(
        [sys.executable, "pipeline/collect.py", "--task", MAZE, "--params", str(bad)],
        cwd=smoke_repo,
        env=_env(),
        capture_output=True,
        text=True,
    )
    assert out.returncode == 2
    assert f"task.{MAZE}.env.maze" in out.stderr and "spiral" in out.stderr


def test_failed_stage_marks_mlflow_run_failed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    with pytest.raises(RuntimeError, match="boom"), stage_run("maze2d-test", "pretrain", 0, {"a": {"b": 1}}, tmp_path):
        raise RuntimeError("boom")
    log_pending(tmp_path)  # what the summarize stage, or `adaptdiffuser mlflow-log` after a failed pipeline, does
    client = MlflowClient(tracking_uri=uri)
    experiment = client.get_experiment_by_name("maze2d-test")
    (run,) = client.search_runs([experiment.experiment_id], "tags.stage = 'pretrain'")
    assert run.info.status == "FAILED"
    assert client.get_run(run.data.tags["mlflow.parentRunId"]).info.status == "FAILED"  # the pipeline run too
    assert run.data.params == {"a.b": "1"} and run.data.tags["stage"] == "pretrain"
    mlflow.set_tracking_uri(None)


def test_committed_lock_holds_the_digest_of_every_source_file_it_names() -> None:
    """``dvc.lock``'s digest of each file of ``src/`` and ``pipeline/`` a stage lists is the file's own: after a code
    change the default pipeline was rerun (``dvc repro``) and its lock and metrics committed, so no stage believes
    older code and no committed output comes from code other than the committed one."""
    lock = yaml.safe_load((REPO / "dvc.lock").read_text())
    stale = []
    for name, entry in lock["stages"].items():
        for dep in entry.get("deps", []):
            file = REPO / dep["path"]
            if dep["path"].split("/")[0] not in ("src", "pipeline") or file.is_dir():
                continue  # a folder's digest is DVC's own (the code stage's fingerprint covers its files)
            if not file.is_file() or hashlib.md5(file.read_bytes()).hexdigest() != dep["md5"]:
                stale.append(f"{name}: {dep['path']}")  # changed, or gone (moved or renamed)
    assert not stale, f"dvc.lock is stale (rerun `dvc repro` and commit its lock and metrics): {stale}"
