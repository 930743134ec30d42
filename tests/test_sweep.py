"""The Optuna sweep on the smoke profile: worker processes sharing a real journal file (and a real PostgreSQL
server when one is installed), MLflow parent and child runs in a temporary sqlite store, early validation of the
search space, and stale trials of killed workers."""

from __future__ import annotations

import dataclasses
import glob
import os
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import optuna
import pytest
import torch
import yaml
from mlflow.tracking import MlflowClient

from adaptdiffuser.config import ConfigError, apply_profile, load_params, params_from_dict
from adaptdiffuser.errors import StageError
from adaptdiffuser.io import write_json
from adaptdiffuser.layout import model_dir
from adaptdiffuser.stages.collect import run_collect
from adaptdiffuser.stages.pretrain import run_pretrain
from adaptdiffuser.stages.reference import run_reference
from adaptdiffuser.tooling.code_fingerprint import fingerprint, fingerprint_path
from adaptdiffuser.tooling.optuna_sweep import (
    _fail_trials_of_dead_workers,
    apply_best,
    load_worker_study,
    make_storage,
    reproduce_command,
    retried_trial_number,
)
from adaptdiffuser.tooling.sweep_trials import (
    family_unseen_objective,
    objective_value,
    plan_trial,
    run_trial,
    trial_raw,
)

REPO = Path(__file__).resolve().parents[1]
TASK = "maze2d-umaze"  # the smoke profile's evolved task, the one a sweep reruns the phases of


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A smoke project after collect, reference and pretrain (what a sweep reuses)."""
    root = tmp_path_factory.mktemp("sweep")
    _copy_pipeline(root)
    apply_profile("smoke", root / "profiles", root / "params.yaml")
    params = load_params(root / "params.yaml")
    assert params.evolve == TASK
    old = os.environ.pop("MLFLOW_TRACKING_URI", None)
    try:
        run_collect(params, TASK, root, progress=False)
        run_reference(params, TASK, root, progress=False)
        run_pretrain(params, TASK, root, torch.device("cpu"), progress=False)
        write_json(root / fingerprint_path(TASK), fingerprint(REPO, "maze2d"))  # the code stage's output
    finally:
        if old is not None:
            os.environ["MLFLOW_TRACKING_URI"] = old
    return root


def _copy_pipeline(root: Path) -> None:
    """What a sweep reads from a project besides params and outputs: dvc.yaml, the stage scripts, the profiles."""
    shutil.copytree(REPO / "profiles", root / "profiles")
    shutil.copytree(REPO / "pipeline", root / "pipeline")
    shutil.copy(REPO / "dvc.yaml", root / "dvc.yaml")


def _sweep(root: Path, *args: str) -> subprocess.CompletedProcess:
    """``adaptdiffuser sweep`` in ``root`` (not a DVC repository: the best trial is not recorded as an experiment
    unless ``--dvc-exp`` says so; tests/test_sharing.py records one)."""
    if "--dvc-exp" not in args:
        args = (*args, "--dvc-exp", "none")
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env['PATH']}"
    return subprocess.run(
        ["adaptdiffuser", "sweep", *args], cwd=root, env=env, capture_output=True, text=True, timeout=600
    )


def _trial_logs(root: Path, study: str, number: int) -> list[str]:
    """The names of the stage logs a sweep trial left, sorted."""
    return sorted(p.name for p in (root / "sweeps" / study / f"trial_{number}" / "logs").iterdir())


def _sweep_runs(root: Path, study: str) -> tuple[object, list]:
    client = MlflowClient(f"sqlite:///{root / 'mlflow.db'}")
    experiment = client.get_experiment_by_name(TASK)
    runs = client.search_runs([experiment.experiment_id], filter_string=f"tags.sweep = '{study}'")
    (parent,) = [r for r in runs if r.data.tags.get("stage") == "sweep"]
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    return client, [parent, *children]


def test_two_workers_share_a_journal_study_and_mlflow_nests_the_trials(project: Path) -> None:
    # one phase on the gain objective: 6 stages a trial (the smoke project's two phases would take 12)
    raw = yaml.safe_load((project / "params.yaml").read_text())
    raw["phases"] = {"phase1": {"previous": 0}}
    (project / "journal.yaml").write_text(yaml.safe_dump(raw))
    out = _sweep(project, "--params", "journal.yaml", "--trials", "2", "--workers", "2", "--apply")
    assert out.returncode == 0, out.stdout + out.stderr
    assert "study adaptdiffuser: {'COMPLETE': 2}" in out.stdout
    assert "dvc exp run -S 'alpha=" in out.stdout and "-S 'evolution.discriminate.max_error=" in out.stdout

    storage = make_storage(None, project, "adaptdiffuser", 30)
    study = optuna.load_study(study_name="adaptdiffuser", storage=storage)
    trials = study.get_trials(states=(optuna.trial.TrialState.COMPLETE,))
    assert len(trials) == 2
    assert len({t.user_attrs["worker_pid"] for t in trials}) == 2  # two processes each ran one trial
    assert all(sorted(t.intermediate_values) == [1] for t in trials)  # a score after the phase
    # each trial ran the commands dvc.yaml declares for the gain objective, and nothing else
    logs = _trial_logs(project, "adaptdiffuser", trials[0].number)
    expected = ("generate", "discriminate", "finetune", "evaluate", "control", "evaluate-control")
    assert logs == sorted(f"{stage}-phase1.log" for stage in expected)

    client, (parent, *children) = _sweep_runs(project, "adaptdiffuser")
    assert len(children) == 2 and parent.info.status == "FINISHED"
    assert parent.data.tags["reproduce"] == reproduce_command(study.best_params)
    for child in children:
        assert set(child.data.params) == {"alpha", "evolution.discriminate.max_error"}
        assert [m.step for m in client.get_metric_history(child.info.run_id, "objective")] == [1]
        # the trial's stage runs, logged by the worker from their run records, nested under the trial's run
        stages = client.search_runs([parent.info.experiment_id], f"tags.mlflow.parentRunId = '{child.info.run_id}'")
        assert sorted(f"{r.data.tags['stage']}-phase{r.data.tags['phase']}.log" for r in stages) == logs
        assert all(r.info.status == "FINISHED" for r in stages)
    assert not list((project / "sweeps" / "adaptdiffuser").glob("trial_*/mlflow-pending/[!.]*"))  # all logged
    pictures = {a.path for a in client.list_artifacts(parent.info.run_id, "optuna")}
    assert pictures == {"optuna/optimization_history.png", "optuna/param_importances.png"}

    # --apply wrote the best values into the params file, which still loads
    applied = load_params(project / "journal.yaml")
    assert applied.alpha == pytest.approx(study.best_params["alpha"])
    assert applied.phase(1).discriminate.max_error == pytest.approx(
        study.best_params["evolution.discriminate.max_error"]
    )


@pytest.mark.parametrize(
    ("mode", "message"), [("run", "not a DVC repository"), ("queue", "--dvc-exp none"), ("later", "one of run")]
)
def test_recording_the_best_trial_is_checked_before_any_trial(project: Path, mode: str, message: str) -> None:
    """The project is not a DVC repository: asking for the best trial as a DVC experiment fails before a trial."""
    raw = yaml.safe_load((project / "params.yaml").read_text())
    raw["sweep"]["study"] = f"dvcexp-{mode}"
    (project / "dvcexp.yaml").write_text(yaml.safe_dump(raw))
    out = _sweep(project, "--trials", "1", "--dvc-exp", mode, "--params", "dvcexp.yaml")
    assert out.returncode == 2 and message in out.stderr, out.stdout + out.stderr
    assert not (project / "sweeps" / f"dvcexp-{mode}.journal").exists()


@pytest.mark.parametrize(
    ("space", "message"),
    [
        ({"alpha": {"low": 10.0, "high": 1.0}}, "sweep.space.alpha: low"),
        ({"alpha": {"low": 0.0, "high": 1.0, "log": True}}, "log range needs low > 0"),
        ({"evolution.discriminate.quantile": {"low": 0.5, "high": 1.5}}, "discriminate.quantile"),
        ({"evolution.discriminate.max_errr": {"low": 0.5, "high": 1.5}}, "no such key"),
    ],
)
def test_a_bad_search_space_is_rejected_before_any_trial(project: Path, space: dict, message: str) -> None:
    raw = yaml.safe_load((project / "params.yaml").read_text())
    raw["sweep"]["space"] = space
    raw["sweep"]["study"] = "bad"
    bad = project / "bad.yaml"
    bad.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match=message):
        load_params(bad)
    out = _sweep(project, "--params", "bad.yaml")
    assert out.returncode == 2 and message.split(":")[0] in out.stderr
    assert not (project / "sweeps" / "bad.journal").exists()


@pytest.mark.parametrize(
    ("key", "stage"),
    [
        ("model.dim", "pretrain@maze2d-umaze"),  # phase 0 would be retrained by dvc repro
        ("task.maze2d-umaze.collect.steps", "collect@maze2d-umaze"),  # so would the expert data
        ("planner.sampler_steps", "reference@maze2d-umaze"),  # the reference scores depend on the planner section
    ],
)
def test_a_key_that_changes_a_reused_stage_is_refused_before_any_trial(project: Path, key: str, stage: str) -> None:
    """Trials reuse collect, reference and pretrain from the last ``dvc repro``: sweeping a key those depend on
    (per dvc.yaml) would silently reuse outputs computed with the old value, so the sweep refuses it."""
    raw = yaml.safe_load((project / "params.yaml").read_text())
    raw["sweep"]["space"] = {key: {"low": 1, "high": 4}}
    raw["sweep"]["study"] = "stale"
    (project / "stale.yaml").write_text(yaml.safe_dump(raw))
    load_params(project / "stale.yaml")  # a valid search space: the refusal comes from what the trials reuse
    out = _sweep(project, "--params", "stale.yaml")
    assert out.returncode == 2, out.stdout + out.stderr
    assert f"sweep.space.{key}: changes stage {stage}" in out.stderr
    assert not (project / "sweeps" / "stale.journal").exists()


def test_trials_run_the_stages_dvc_yaml_declares(tmp_path: Path) -> None:
    """The trial plan is read from dvc.yaml: a stage added to the phase chain runs in every trial, and an objective
    whose stage dvc.yaml lacks is refused."""
    _copy_pipeline(tmp_path)
    raw = yaml.safe_load(apply_profile("smoke", tmp_path / "profiles", tmp_path / "params.yaml").read_text())
    trial = trial_raw(raw, {})
    plan = plan_trial(tmp_path, trial, "gain")
    assert [stage.name for stage in plan.reused] == sorted(stage.name for stage in plan.reused)
    assert {stage.kind for stage in plan.reused} == {"code", "collect", "reference", "pretrain"}
    assert set(plan.inputs) >= {"data/maze2d-umaze/dataset.parquet", "models/maze2d-umaze/phase0"}
    assert plan.phases[0].metrics == {
        "evaluate": "metrics/tasks/maze2d-umaze/phase1.json",
        "control": "metrics/tasks/maze2d-umaze/phase1-control.json",
    }
    names = [stage.name for stage in plan.phases[0].stages]
    assert names.index("finetune@phase1") < names.index("evaluate@phase1") < names.index("evaluate-control@phase1")

    pipeline = yaml.safe_load((tmp_path / "dvc.yaml").read_text())
    extra = dict(pipeline["stages"]["evaluate"], do=dict(pipeline["stages"]["evaluate"]["do"]))
    extra["do"]["cmd"] = "python pipeline/evaluate.py --task ${evolve} --phase ${key} --again"
    extra["do"]["outs"] = ["results/${evolve}/${key}-again"]
    extra["do"]["deps"] = [*extra["do"]["deps"], "results/${evolve}/${key}"]
    extra["do"].pop("metrics", None)
    pipeline["stages"]["evaluate-again"] = extra
    pipeline["stages"]["evaluate-control"]["do"]["deps"].append("results/${evolve}/${key}-again")
    del pipeline["stages"]["evaluate-unseen"]
    (tmp_path / "dvc.yaml").write_text(yaml.safe_dump(pipeline, sort_keys=False))
    names = [stage.name for stage in plan_trial(tmp_path, trial, "gain").phases[1].stages]
    assert names.index("evaluate@phase2") < names.index("evaluate-again@phase2")
    assert names.index("evaluate-again@phase2") < names.index("evaluate-control@phase2")
    with pytest.raises(StageError, match="dvc.yaml has no stage evaluate-unseen@phase1"):
        plan_trial(tmp_path, trial, "unseen")


def test_a_trial_plays_start_states_of_its_own_on_both_sets(tmp_path: Path) -> None:
    """A trial's evaluation and held-out start states are the sweep's (``sweep.evaluate_seed``,
    ``sweep.held_out_seed``), also where the swept task's entry sets its own, so no trial plays a state the pipeline
    reports on."""
    raw = yaml.safe_load(apply_profile("smoke", REPO / "profiles", tmp_path / "params.yaml").read_text())
    raw.setdefault("task", {}).setdefault(TASK, {})["evaluate"] = {"seed": 1100, "held_out_seed": 7100}
    base = params_from_dict(raw)
    pipeline = base.resolve(TASK).evaluate
    assert pipeline.held_out_episodes > 0 and (pipeline.seed, pipeline.held_out_seed) == (1100, 7100)
    trial = params_from_dict(trial_raw(raw, {})).resolve(TASK).evaluate
    assert (trial.seed, trial.held_out_seed) == (base.sweep.evaluate_seed, base.sweep.held_out_seed)
    played = {trial.seed + s for s in base.seeds} | {trial.held_out_seed + s for s in base.seeds}
    assert not played & ({pipeline.seed + s for s in base.seeds} | {pipeline.held_out_seed + s for s in base.seeds})


def test_the_unseen_objectives_read_the_family_figure_of_the_unseen_metrics_file() -> None:
    """``unseen`` is the family's figure of its unseen-task file (Maze2D: 100 x coin both-rate, KUKA: the
    pick-and-place score), ``mix`` weighs it against the score; a task without an unseen task has none."""
    maze = load_params(REPO / "params.yaml")
    metrics = {"evaluate": {"score_mean": 80.0}, "unseen": {"gold_coin": {"both_rate": 0.4}, "n_seeds": 1}}
    assert objective_value(dataclasses.replace(maze.sweep, objective="score"), metrics) == 80.0
    unseen = dataclasses.replace(maze.sweep, objective="unseen")
    assert objective_value(unseen, metrics, family_unseen_objective(maze)) == pytest.approx(40.0)
    mix = dataclasses.replace(maze.sweep, objective="mix", unseen_weight=0.25)
    assert objective_value(mix, metrics, family_unseen_objective(maze)) == pytest.approx(0.75 * 80 + 0.25 * 40)
    kuka = params_from_dict(
        {
            "tasks": ["kuka-stacking"],
            "unseen_tasks": ["kuka-stacking"],
            "evolve": "kuka-stacking",
            "task": {"kuka-stacking": {"family": "kuka"}},
            "sweep": {"objective": "unseen"},
        }  # fmt: skip
    )
    placed = {"evaluate": {"score_mean": 5.0}, "unseen": {"pick_place": {"score_mean": 12.5}}}
    assert objective_value(kuka.sweep, placed, family_unseen_objective(kuka)) == 12.5
    hopper = params_from_dict(
        {
            "tasks": ["hopper-medium"],
            "unseen_tasks": [],
            "evolve": "hopper-medium",
            "task": {"hopper-medium": {"family": "locomotion"}},
        }  # fmt: skip
    )
    assert family_unseen_objective(hopper) is None
    with pytest.raises(StageError, match="has no unseen task"):
        objective_value(unseen, metrics, None)


def test_apply_changes_only_the_swept_lines_of_the_repository_params(tmp_path: Path) -> None:
    repo_params = Path(__file__).resolve().parents[1] / "params.yaml"
    target = tmp_path / "params.yaml"
    commented = {"alpha: 10.0\n": "alpha: 10.0  # guidance\n", "max_error: 1.0\n": "max_error: 1.0  # cells\n"}
    text = repo_params.read_text()
    for old, new in commented.items():  # a file as a user comments it
        assert text.count(old) == 1
        text = text.replace(old, new)
    target.write_text(text)
    apply_best(target, {"alpha": 42.5, "evolution.discriminate.max_error": 1.25})
    before, after = text.splitlines(), target.read_text().splitlines()
    assert len(before) == len(after)
    changed = [(old, new) for old, new in zip(before, after, strict=True) if old != new]
    assert [new.split("#")[0].split() for _, new in changed] == [["alpha:", "42.5"], ["max_error:", "1.25"]]
    assert all("#" in new for _, new in changed)  # the comments stay
    assert load_params(target).alpha == 42.5


@pytest.mark.parametrize(("startup", "pruned"), [(1, True), (2, False)])
def test_workers_prune_with_the_sweeps_pruner(tmp_path: Path, startup: int, pruned: bool) -> None:
    """A worker's study prunes as ``sweep.pruner_startup_trials`` says (not Optuna's default of 5 startup trials)."""
    sweep = params_from_dict({"sweep": {"pruner_startup_trials": startup}}).sweep
    optuna.create_study(study_name="p", storage=make_storage(None, tmp_path, "p", 30), direction="maximize")
    study = load_worker_study(None, tmp_path, "p", sweep, 0)
    first = study.ask()
    first.report(10.0, 1)
    study.tell(first, 10.0)
    second = study.ask()
    second.report(0.0, 1)
    assert bool(second.should_prune()) is pruned


def test_trials_of_a_killed_worker_are_failed_and_retried_once(tmp_path: Path) -> None:
    storage = make_storage(str(tmp_path / "s.journal"), tmp_path, "stale", 30)
    study = optuna.create_study(study_name="stale", storage=storage)
    trial = study.ask({"alpha": optuna.distributions.FloatDistribution(1.0, 10.0)})
    trial.set_user_attr("worker_pid", 4242)
    other = study.ask({"alpha": optuna.distributions.FloatDistribution(1.0, 10.0)})
    other.set_user_attr("worker_pid", 777)
    _fail_trials_of_dead_workers(study, {4242})
    states = {t.number: t.state for t in study.trials}
    assert states[trial.number] == optuna.trial.TrialState.FAIL
    assert states[other.number] == optuna.trial.TrialState.RUNNING  # a live worker's trial is left alone
    (waiting,) = study.get_trials(states=(optuna.trial.TrialState.WAITING,))
    assert waiting.params == {"alpha": trial.params["alpha"]} and retried_trial_number(waiting) == trial.number
    assert "worker_pid" not in waiting.user_attrs  # the worker that runs the retry sets its own
    _fail_trials_of_dead_workers(study, {4242})  # nothing of that worker is left running: no second retry
    assert len(study.trials) == 3


def _postgres_bin() -> Path | None:
    found = shutil.which("initdb")
    if found:
        return Path(found).parent
    candidates = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    return Path(candidates[-1]).parent if candidates else None


def _user_exists(name: str) -> bool:
    import pwd

    try:
        pwd.getpwnam(name)
    except KeyError:
        return False
    return True


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def postgres():
    """A real PostgreSQL server on loopback, in a temporary data directory (as user postgres when run as root,
    since the server refuses to run as root)."""
    bindir = _postgres_bin()
    if bindir is None:
        pytest.skip("PostgreSQL server binaries (initdb, pg_ctl) are not installed; .ci/run installs them")
    base = Path(tempfile.mkdtemp(prefix="adaptdiffuser-pg-"))
    base.chmod(0o755)
    data = base / "pgdata"
    sockets = base / "pgsock"
    sockets.mkdir()
    prefix: list[str] = []
    if os.geteuid() == 0:
        if shutil.which("runuser") is None or not _user_exists("postgres"):
            pytest.skip("running as root without runuser or a postgres user: cannot start the server unprivileged")
        prefix = ["runuser", "-u", "postgres", "--"]
        shutil.chown(base, "postgres")
        shutil.chown(sockets, "postgres")
    port = _free_port()
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}  # the server keeps inherited pipes open
    initdb = [*prefix, str(bindir / "initdb"), "-D", str(data), "-U", "postgres", "-A", "trust"]
    subprocess.run(initdb, check=True, **quiet)
    options = f"-p {port} -k {sockets} -c listen_addresses=127.0.0.1"
    pg_ctl = [*prefix, str(bindir / "pg_ctl"), "-D", str(data), "-l", str(base / "server.log")]
    subprocess.run([*pg_ctl, "-o", options, "-w", "start"], check=True, **quiet)
    try:
        yield f"postgresql://postgres@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run([*pg_ctl, "-m", "immediate", "stop"], **quiet)
        shutil.rmtree(base, ignore_errors=True)


def test_the_same_sweep_runs_on_postgresql(project: Path, postgres: str) -> None:
    raw = yaml.safe_load((project / "params.yaml").read_text())
    # the storage is what this test is about: one phase scored on its own is 4 stages a trial (the journal test
    # above runs the gain objective's 12)
    raw["phases"] = {"phase1": {"previous": 0}}
    raw["sweep"] |= {"study": "on-postgres", "objective": "score"}
    (project / "pg.yaml").write_text(yaml.safe_dump(raw))
    out = _sweep(project, "--params", "pg.yaml", "--trials", "2", "--workers", "2", "--storage", postgres)
    assert out.returncode == 0, out.stdout + out.stderr
    study = optuna.load_study(study_name="on-postgres", storage=postgres)
    trials = study.get_trials(states=(optuna.trial.TrialState.COMPLETE,))
    assert len(trials) == 2
    logs = _trial_logs(project, "on-postgres", trials[0].number)
    assert logs == sorted(f"{stage}-phase1.log" for stage in ("generate", "discriminate", "finetune", "evaluate"))
    _, (parent, *children) = _sweep_runs(project, "on-postgres")
    assert len(children) == 2 and parent.data.tags["storage"] == postgres


def test_a_trial_sweeps_a_locomotion_task_on_its_gain_over_the_control(tmp_path: Path) -> None:
    """``sweep.task: hopper-medium``: the trial evolves the hopper (not ``evolve``), runs each phase's control and
    scores the phase by its paired gain, evaluated on the sweep's own episodes."""
    name = "hopper-medium"
    _copy_pipeline(tmp_path)
    raw = yaml.safe_load(apply_profile("smoke", tmp_path / "profiles", tmp_path / "params.yaml").read_text())
    raw["phases"] = {"phase1": {"previous": 0}}
    raw["sweep"].update(
        task=name, objective="gain", space={"evolution.discriminate.quantile": {"low": 0.2, "high": 0.8}}
    )
    base = params_from_dict(raw)
    assert base.evolve == TASK and base.resolve(name).evaluate.seed != base.sweep.evaluate_seed
    device = torch.device("cpu")
    old = os.environ.pop("MLFLOW_TRACKING_URI", None)
    try:
        run_collect(base, name, tmp_path, progress=False)
        run_reference(base, name, tmp_path, progress=False)
        run_pretrain(base, name, tmp_path, device, progress=False)
        write_json(tmp_path / fingerprint_path(name), fingerprint(REPO, "locomotion"))  # the code stage's output
        trial = trial_raw(raw, {"evolution.discriminate.quantile": 0.3})
        params = params_from_dict(trial)
        assert params.evolve == name and params.phase(1).discriminate.quantile == 0.3
        assert params.resolve(name).evaluate.seed == base.sweep.evaluate_seed
        reports: list[tuple[int, float, dict]] = []
        folder = tmp_path / "trial"
        value = run_trial(trial, base.sweep, tmp_path, folder, "cpu", lambda k, v, m: reports.append((k, v, m)))
    finally:
        if old is not None:
            os.environ["MLFLOW_TRACKING_URI"] = old
    ((k, reported, metrics),) = reports
    assert k == 1 and value == reported == metrics["control"]["gain_mean"]
    assert "unseen" not in metrics  # the gain objective reads no unseen-task metrics
    assert (folder / model_dir(name, 1, 0, control=True)).exists()
    assert reproduce_command({"evolve": name}) == "dvc exp run -S 'evolve=hopper-medium'"
