"""`adaptdiffuser pool`: a science run's training seeds run apart (one run's folder, or one DVC experiment, a seed)
and pooled give the metrics and the summary of the one run over all of them; runs that differ in more than their
seeds do not pool."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from smoke_project import REPO, make_smoke_project, only_tasks, run_queue, run_tool

from adaptdiffuser.errors import StageError
from adaptdiffuser.seed_metrics import over_seeds
from adaptdiffuser.stages.pool import pool_runs, summary_of
from adaptdiffuser.tooling.dvc_experiments import experiment_commit

SAVED = REPO / "metrics" / "runs" / "science-umaze-7ba7674"  # a real three-seed run (U-Maze, both recipes)
TASK = "maze2d-umaze"
PASS = "maze2d-umaze-rollouts"  # a per-pass copy, as scripts/science_maze.sh keeps one a recipe


#: the run's reference, which its save left out (the pinned commit holds it as the run wrote it)
REFERENCE = REPO / "metrics" / "tasks" / TASK / "reference.json"


@pytest.fixture(scope="module")
def tasks(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The three-seed run's task metrics, whole: the saved files and the reference."""
    folder = tmp_path_factory.mktemp("run") / "tasks"
    shutil.copytree(SAVED / "metrics" / "tasks", folder)
    shutil.copy2(REFERENCE, folder / TASK / "reference.json")
    return folder


def one_seed_run(folder: Path, seed: int, tasks: Path) -> Path:
    """What the saved run would be had it run training seed ``seed`` alone: each metrics file as ``over_seeds``
    writes it for that one seed (a seed's training, generation and evaluation depend on it alone)."""
    raw = yaml.safe_load((SAVED / "params.yaml").read_text()) | {"seeds": [seed]}
    folder.mkdir(parents=True)
    (folder / "params.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))
    code = {"path": f"code/{TASK}.json", "md5": "1" * 32}  # the task's code digest, as DVC records it
    lock = {"schema": "2.0", "stages": {f"pretrain@{TASK}": {"cmd": "python pipeline/pretrain.py", "deps": [code]}}}
    (folder / "dvc.lock").write_text(yaml.safe_dump(lock))
    shutil.copy2(SAVED / "run.json", folder / "run.json")
    for where in (folder / "metrics" / "tasks", folder / "metrics" / "science" / PASS):
        for path in tasks.glob("*/*.json"):
            content = json.loads(path.read_text())
            if "seeds" in content:
                content = over_seeds({seed: content["seeds"][str(seed)]})
            target = where / path.relative_to(tasks)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(json.dumps(content))
    return folder


def test_seeds_run_apart_pool_into_the_three_seed_run(tasks: Path, tmp_path: Path) -> None:
    runs = [one_seed_run(tmp_path / f"seed{seed}", seed, tasks) for seed in (2, 0, 1)]
    into = tmp_path / "pooled"
    lines = pool_runs(runs, into)

    originals = sorted(tasks.glob("*/*.json"))
    assert len(originals) == 13  # the reference, phases 0-2, their controls, unseen-task twins, discriminators
    for where in (into / "metrics" / "tasks", into / "metrics" / "science" / PASS):
        for path in originals:
            pooled = json.loads((where / path.relative_to(tasks)).read_text())
            assert pooled == json.loads(path.read_text()), path.name
    expected = summary_of(yaml.safe_load((SAVED / "params.yaml").read_text()), tasks)
    assert json.loads((into / "metrics" / "summary.json").read_text()) == expected
    assert json.loads((into / "metrics" / "science" / f"{PASS}.json").read_text()) == expected
    assert expected[TASK]["phase_2"]["n_seeds"] == 3 and expected[TASK]["phase_2"]["gain_stderr"] is not None
    assert yaml.safe_load((into / "params.yaml").read_text())["seeds"] == [0, 1, 2]
    assert [record["folder"] for record in json.loads((into / "run.json").read_text())["pooled"]] == list(
        map(str, runs)
    )
    assert any("seeds [0, 1, 2] pooled, summary" in line for line in lines)
    assert not any("CPUs" in line for line in lines)  # one CPU (the saved run's record names none)


def test_seeds_from_two_cpus_are_pooled_and_said_so(tasks: Path, tmp_path: Path) -> None:
    runs = [one_seed_run(tmp_path / f"seed{seed}", seed, tasks) for seed in (0, 1)]
    for run, cpu in zip(runs, ("AMD EPYC, 2 cores, AVX-512", "AMD EPYC, 2 cores, no AVX-512"), strict=True):
        (run / "run.json").write_text(json.dumps({"commit": "abc", "profile": "science-umaze", "cpu": cpu}))
    lines = pool_runs(runs, tmp_path / "pooled")
    cpus = ("AMD EPYC, 2 cores, AVX-512", "AMD EPYC, 2 cores, no AVX-512")
    assert lines[0] == f"the seeds ran on 2 CPUs: {cpus[0]}; {cpus[1]} (say so beside the results)"
    records = json.loads((tmp_path / "pooled" / "run.json").read_text())["pooled"]
    assert [record["cpu"] for record in records] == ["AMD EPYC, 2 cores, AVX-512", "AMD EPYC, 2 cores, no AVX-512"]


def test_runs_without_a_lock_pool_on_their_params_and_metrics(tasks: Path, tmp_path: Path) -> None:
    runs = [one_seed_run(tmp_path / f"seed{seed}", seed, tasks) for seed in (0, 1)]
    (runs[1] / "dvc.lock").write_text((runs[1] / "dvc.lock").read_text().replace("1" * 32, "0" * 32))
    with pytest.raises(StageError, match="ran other code"):
        pool_runs(runs, tmp_path / "pooled")
    (runs[1] / "dvc.lock").unlink()  # a folder that keeps what a reader needs: its code is not checked
    assert any("seeds [0, 1] pooled, summary" in line for line in pool_runs(runs, tmp_path / "pooled"))


def test_a_phase_one_run_lacks_is_left_out_and_the_set_has_no_summary(tasks: Path, tmp_path: Path) -> None:
    runs = [one_seed_run(tmp_path / f"seed{seed}", seed, tasks) for seed in (0, 1)]
    (runs[1] / "metrics" / "tasks" / TASK / "phase2.json").unlink()  # a run stopped before phase 2's evaluation
    lines = pool_runs(runs, tmp_path / "pooled")
    assert f"tasks: {TASK}/phase2.json left out (not in every run)" in lines
    assert any(line.startswith("tasks: seeds [0, 1] pooled, no summary") for line in lines)
    assert not (tmp_path / "pooled" / "metrics" / "summary.json").exists()
    assert (tmp_path / "pooled" / "metrics" / "science" / f"{PASS}.json").exists()  # the complete set has its own


def test_runs_whose_phase_0_was_imported_or_trained_pool_and_say_which(tasks: Path, tmp_path: Path) -> None:
    imported, trained = one_seed_run(tmp_path / "a", 0, tasks), one_seed_run(tmp_path / "b", 1, tasks)
    raw = yaml.safe_load((imported / "params.yaml").read_text())
    raw |= {"pretrained": {TASK: "../phase0/maze2d-umaze"}, "pretrain_tasks": []}
    (imported / "params.yaml").write_text(yaml.safe_dump(raw))
    lines = pool_runs([imported, trained], tmp_path / "pooled")
    assert any("seeds [0, 1] pooled, summary" in line for line in lines)
    assert any("phases 0 came from different sources" in line for line in lines)
    records = json.loads((tmp_path / "pooled" / "run.json").read_text())["pooled"]
    sources = [record["phase0_source"] for record in records]
    assert sources[0] == {"pretrained": {TASK: "../phase0/maze2d-umaze"}, "pretrain_tasks": []}
    assert sources[1] == {"pretrained": None, "pretrain_tasks": None}  # the profile's: every task trained here

    raw["pretrain"]["steps"] += 1  # phase 0 by another recipe: refused, wherever it came from
    (imported / "params.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(StageError, match="differ in 'pretrain.steps'"):
        pool_runs([imported, trained], tmp_path / "pooled")


@pytest.mark.parametrize("change", ["params", "seeds", "code", "reference"])
def test_runs_that_differ_in_more_than_their_seeds_do_not_pool(change: str, tasks: Path, tmp_path: Path) -> None:
    first, second = one_seed_run(tmp_path / "a", 0, tasks), one_seed_run(tmp_path / "b", 1, tasks)
    if change == "params":
        raw = yaml.safe_load((second / "params.yaml").read_text())
        raw["pretrain"]["steps"] += 1
        (second / "params.yaml").write_text(yaml.safe_dump(raw))
        message = "differ in 'pretrain.steps', not only in seeds"
    elif change == "seeds":
        second = one_seed_run(tmp_path / "c", 0, tasks)
        message = "training seed 0 is in both"
    elif change == "code":
        lock = (second / "dvc.lock").read_text()
        digest = yaml.safe_load(lock)["stages"][f"pretrain@{TASK}"]["deps"]
        md5 = next(dep["md5"] for dep in digest if dep["path"] == f"code/{TASK}.json")
        (second / "dvc.lock").write_text(lock.replace(md5, "0" * 32))
        message = f"ran other code (code/{TASK}.json differs)"
    else:
        path = second / "metrics" / "tasks" / TASK / "reference.json"
        path.write_text(json.dumps(json.loads(path.read_text()) | {"r_max": 1.0}))
        message = "reference.json differs between the runs"
    into = tmp_path / "pooled"
    into.mkdir()
    (into / "kept.txt").write_text("an earlier pool")
    with pytest.raises(StageError, match=message.replace("(", r"\(").replace(")", r"\)")):
        pool_runs([first, second], into)
    assert (into / "kept.txt").read_text() == "an earlier pool"  # nothing half-written


def test_the_command_line_says_in_one_line_what_is_not_a_saved_run(tasks: Path, tmp_path: Path) -> None:
    run = one_seed_run(tmp_path / "a", 0, tasks)
    (tmp_path / "b").mkdir()
    cli = [str(Path(sys.executable).parent / "adaptdiffuser"), "pool", str(run), str(tmp_path / "b"), "--into", "x"]
    out = subprocess.run(cli, capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 2, out.stdout + out.stderr
    assert out.stderr.strip() == f"error: {tmp_path / 'b'} is not a run's folder: it has no params.yaml"


def test_a_file_the_saves_left_out_as_committed_comes_from_the_runs_commit(tasks: Path, tmp_path: Path) -> None:
    repo = tmp_path / "repo"  # the repository the runs were pinned in, holding the reference they wrote unchanged
    (repo / "metrics" / "tasks" / TASK).mkdir(parents=True)
    shutil.copy2(REFERENCE, repo / "metrics" / "tasks" / TASK / "reference.json")
    for other in (f"{TASK}/phase3.json", "another-task/reference.json"):  # none of the runs' seeds or tasks
        (repo / "metrics" / "tasks" / other).parent.mkdir(parents=True, exist_ok=True)
        (repo / "metrics" / "tasks" / other).write_text(json.dumps({"seeds": {"0": {}}} if "phase" in other else {}))
    git = ["git", "-C", str(repo), "-c", "user.email=t@example.com", "-c", "user.name=t"]
    for command in (["init", "-q"], ["add", "-A"], ["commit", "-qm", "reference"]):
        subprocess.run([*git, *command], check=True)
    commit = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    runs = [one_seed_run(tmp_path / f"seed{seed}", seed, tasks) for seed in (0, 1)]
    for run in runs:  # as a run's folder holds them: without the reference, the commit in run.json
        (run / "metrics" / "tasks" / TASK / "reference.json").unlink()
        (run / "run.json").write_text(json.dumps({"commit": commit, "profile": "science-umaze"}))
    into = tmp_path / "pooled"
    pool_runs(runs, into, repo=repo)
    assert (into / "metrics" / "tasks" / TASK / "reference.json").read_bytes() == REFERENCE.read_bytes()
    assert not (into / "metrics" / "tasks" / TASK / "phase3.json").exists()
    assert not (into / "metrics" / "tasks" / "another-task").exists()
    assert json.loads((into / "metrics" / "summary.json").read_text())[TASK]["phase_2"]["n_seeds"] == 2


def test_a_pass_copy_of_another_tasks_committed_metrics_is_not_pooled(tasks: Path, tmp_path: Path) -> None:
    runs = [one_seed_run(tmp_path / f"seed{seed}", seed, tasks) for seed in (0, 1)]
    for run in runs:  # as scripts/science_maze.sh copied metrics/tasks/ whole at 25aa8f9
        foreign = run / "metrics" / "science" / PASS / "maze2d-medium"  # not a task of these runs: seed 0 in each
        foreign.mkdir(parents=True)
        (foreign / "phase0.json").write_text(json.dumps(over_seeds({0: {"score_mean": 1.0, "n_episodes": 1}})))
    into = tmp_path / "pooled"
    pool_runs(runs, into)
    assert (into / "metrics" / "science" / PASS / TASK / "phase0.json").exists()
    assert not (into / "metrics" / "science" / PASS / "maze2d-medium").exists()


def test_a_seed_in_two_runs_files_is_refused(tasks: Path, tmp_path: Path) -> None:
    runs = [one_seed_run(tmp_path / f"seed{seed}", seed, tasks) for seed in (0, 1)]
    path = runs[1] / "metrics" / "tasks" / TASK / "phase1.json"  # a file that says seed 0 in the run of seed 1
    seed0 = json.loads((runs[0] / "metrics" / "tasks" / TASK / "phase1.json").read_text())
    path.write_text(json.dumps(over_seeds({0: seed0["seeds"]["0"]})))
    with pytest.raises(StageError, match="holds seed 0, which another run's file holds too"):
        pool_runs(runs, tmp_path / "pooled")


@pytest.mark.e2e
def test_seeds_queued_as_dvc_experiments_run_on_two_workers_and_pool(tmp_path: Path) -> None:
    phase0_of_the_maze = only_tasks([TASK], unseen_tasks=[TASK], evolve=None, phases={})
    (tmp_path / "project").mkdir()
    project = make_smoke_project(tmp_path / "project", run_tool, edit=phase0_of_the_maze)
    out = run_tool(["adaptdiffuser", "seeds", "queue", "0", "1", "--name", "tiny"], project)
    assert "queued tiny-seed0 tiny-seed1" in out and "--exp tiny-seed0 --exp tiny-seed1" in out
    status = run_queue(project, timeout_s=900.0)
    assert status.count("Success") == 2, status

    into = tmp_path / "pooled"
    cli = ["adaptdiffuser", "pool", "--exp", "tiny-seed1", "--exp", "tiny-seed0", "--into", str(into)]
    assert "tasks: seeds [0, 1] pooled, summary" in run_tool(cli, project)
    assert yaml.safe_load((into / "params.yaml").read_text())["seeds"] == [0, 1]
    records = json.loads((into / "run.json").read_text())["pooled"]
    assert [record["experiment"] for record in records] == ["tiny-seed1", "tiny-seed0"]
    pooled = sorted((into / "metrics" / "tasks" / TASK).glob("*.json"))
    assert {path.name for path in pooled} >= {"reference.json", "phase0.json", "phase0-unseen.json"}
    for path in pooled:  # each seed's metrics as its experiment measured them
        content = json.loads(path.read_text())
        for seed in (0, 1):
            commit = experiment_commit(project, f"tiny-seed{seed}")
            shown = run_tool(["git", "show", f"{commit}:metrics/tasks/{TASK}/{path.name}"], project)
            theirs = json.loads(shown)
            if "seeds" in theirs:
                assert content["seeds"][str(seed)] == theirs["seeds"][str(seed)], path.name
            else:  # the reference: no seed's, the same in both
                assert content == theirs, path.name
    summary = json.loads((into / "metrics" / "summary.json").read_text())
    assert summary[TASK]["phase_0"]["n_seeds"] == 2
