"""scripts/long_run.sh: a run in its own clone pinned to a commit, killed part-way, continued by one command."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
import yaml
from smoke_project import REPO, make_smoke_project, run_tool

from adaptdiffuser.stages.pool import summary_of

SCRIPT = str(REPO / "scripts" / "long_run.sh")
MAZE = "maze2d-umaze"


def _phase0_of_one_task(path: Path) -> None:
    """Phase 0 of the maze task alone over two training seeds, with a pretraining long enough to be killed between
    its checkpoints (the run sets them 100 steps apart: ``long_run.sh start --set``)."""
    raw = yaml.safe_load(path.read_text())
    raw.update(tasks=[MAZE], collect_tasks=[MAZE], unseen_tasks=[MAZE], evolve=None, phases={}, seeds=[0, 1])
    raw["pretrain"] |= {"steps": 600}
    path.write_text(yaml.safe_dump(raw, sort_keys=False))


@pytest.mark.e2e
def test_a_killed_long_run_continues_with_one_command(tmp_path: Path) -> None:
    (tmp_path / "project").mkdir()
    project = make_smoke_project(tmp_path / "project", run_tool, edit=_phase0_of_one_task)
    earlier = Path("metrics/science/earlier.json")  # a result the commit holds: not the run's to save
    (project / earlier).parent.mkdir(parents=True)
    (project / earlier).write_text("{}\n")
    run_tool(["git", "add", str(earlier)], project)
    run_tool(["git", "commit", "-q", "-m", "an earlier result"], project)
    head = run_tool(["git", "rev-parse", "HEAD"], project).strip()
    run_tool(["git", "commit", "-q", "--allow-empty", "-m", "later work"], project)  # the run stays on `head`
    folder = tmp_path / "run"
    venv = ["--venv", sys.prefix]
    every = "pretrain.checkpoint_every=100"
    start = ["bash", SCRIPT, "start", str(folder), "--from", str(project), "--commit", head, "--set", every, *venv]
    out = run_tool(start, tmp_path)
    assert f"pinned {folder} at {head}" in out
    assert yaml.safe_load((folder / "params.yaml").read_text())["pretrain"]["checkpoint_every"] == 100
    seed1 = folder / "models" / ".resume" / f"{MAZE}-phase0-seed1.pt"
    # stop the run once the second seed's pretraining has written a whole resume state (not only its hidden
    # temporary file; the first seed's training is finished by then): SIGTERM to its process group, and the stage
    # ends its step and writes its state there before it goes
    _wait_for(seed1.exists, folder)
    run_tool(["bash", SCRIPT, "stop", str(folder)], tmp_path)
    log = (folder / "long_run.log").read_text()
    stops = re.findall(r"SIGTERM: stopping after step (\d+),", log)
    assert len(stops) == 1, log  # seed 1's pretraining took the stop
    stopped = int(stops[0])
    status = run_tool(["bash", SCRIPT, "status", str(folder)], tmp_path)
    assert f"resume state: {MAZE}-phase0-seed1.pt (step {stopped})" in status
    assert f"set: {every}" in status
    run_tool(["bash", SCRIPT, "resume", str(folder)], tmp_path)
    pid = int((folder / "long_run.pid").read_text())
    # then killed outright (SIGKILL, as when the machine goes) once the resumed training has passed a checkpoint
    _wait_for(lambda: _state_step(seed1) > stopped, folder)
    os.killpg(pid, signal.SIGKILL)
    while subprocess.run(["kill", "-0", str(pid)], capture_output=True).returncode == 0:
        time.sleep(0.1)

    status = run_tool(["bash", SCRIPT, "status", str(folder)], tmp_path)
    assert f"commit: {head[:7]}" in status and "not running" in status
    assert f"resume state: {MAZE}-phase0-seed0.pt (step 600)" in status  # the first seed, finished
    assert f"resume state: {MAZE}-phase0-seed1.pt (step " in status
    refused = subprocess.run(["bash", SCRIPT, "start", str(folder)], capture_output=True, text=True)
    assert refused.returncode == 2 and "exists: continue it with" in refused.stderr
    saved = tmp_path / "saved"  # what the run measured so far, to commit before the machine goes
    run_tool(["bash", SCRIPT, "save", str(folder), "--into", str(saved)], tmp_path)
    assert json.loads((saved / "run.json").read_text())["commit"] == head
    (saved / "stale.txt").write_text("replaced whole by the next save")

    run_tool(["bash", SCRIPT, "resume", str(folder), "--foreground"], tmp_path)
    log = (folder / "long_run.log").read_text()
    # the first seed is not trained again, the second goes on from its checkpoint, not from step 0
    assert "resuming training from step 600" in log and f"resuming training from step {stopped} " in log
    assert any(f"resuming training from step {step} " in log for step in range(100, 600, 100))
    status = run_tool(["bash", SCRIPT, "status", str(folder)], tmp_path)
    assert "finished: ended by itself" in status and "0 left" in status and "resume state:" not in status
    assert run_tool(["git", "rev-parse", "HEAD"], folder).strip() == head
    assert (folder / f"metrics/tasks/{MAZE}/phase0-unseen.json").exists()

    out = run_tool(["bash", SCRIPT, "save", str(folder), "--into", str(saved)], tmp_path)
    assert f"in {saved}" in out and not (saved / "stale.txt").exists()
    record = json.loads((saved / "run.json").read_text())
    assert record["commit"] == head and record["running"] is False and record["settings"] == [every]
    assert record["cpu"].endswith(("AVX-512", "no AVX-512")) and f"{os.cpu_count()} cores" in record["cpu"]
    assert (saved / "params.yaml").read_bytes() == (folder / "params.yaml").read_bytes()
    assert (saved / "dvc.lock").read_bytes() == (folder / "dvc.lock").read_bytes()
    files = [path.relative_to(saved) for path in sorted((saved / "metrics").rglob("*")) if path.is_file()]
    assert Path(f"metrics/tasks/{MAZE}/phase0-unseen.json") in files and earlier not in files
    for file in files:  # the run's own measurements: as the run wrote them, not as the pinned commit holds them
        assert (saved / file).read_bytes() == (folder / file).read_bytes()
        committed = subprocess.run(["git", "show", f"{head}:{file}"], cwd=folder, capture_output=True)
        assert committed.returncode != 0 or committed.stdout != (folder / file).read_bytes()


@pytest.mark.e2e
def test_a_run_saved_with_what_it_carries_continues_where_its_machine_is_gone(tmp_path: Path) -> None:
    (tmp_path / "project").mkdir()
    project = make_smoke_project(tmp_path / "project", run_tool, edit=_phase0_of_one_task)
    head = run_tool(["git", "rev-parse", "HEAD"], project).strip()
    every = "pretrain.checkpoint_every=100"
    pinned = ["--from", str(project), "--commit", head, "--set", every, "--venv", sys.prefix]
    first = tmp_path / "first"
    run_tool(["bash", SCRIPT, "start", str(first), *pinned], tmp_path)
    _wait_for((first / "models" / ".resume" / f"{MAZE}-phase0-seed1.pt").exists, first)
    run_tool(["bash", SCRIPT, "stop", str(first)], tmp_path)
    (stopped,) = re.findall(r"SIGTERM: stopping after step (\d+),", (first / "long_run.log").read_text())
    saved = tmp_path / "saved"
    for bad in ("../run", "/etc", ".", "models/..", ".git", "long_run.log"):  # never outside it, nor all of it
        refused = subprocess.run(["bash", SCRIPT, "save", str(first), "--into", str(saved), "--carry", bad],
                                 capture_output=True, text=True)  # fmt: skip
        assert refused.returncode == 2 and "not a path of the run's own files" in refused.stderr, bad
    assert not saved.exists()
    run_tool(["bash", SCRIPT, "save", str(first), "--into", str(saved), "--carry", "models/.resume"], tmp_path)
    carried = sorted(path.name for path in (saved / "carry" / "models" / ".resume").iterdir())
    assert f"{MAZE}-phase0-seed0.pt" in carried and f"{MAZE}-phase0-seed1.pt" in carried
    assert not [name for name in carried if name.startswith(".")]  # no atomic write's temporary file
    assert json.loads((saved / "run.json").read_text())["carried"] == ["models/.resume"]
    shutil.rmtree(first)  # the machine is gone: only the committed save is left

    # refused in one line before anything is cloned: another run's save, a save that carries nothing, --restore
    # outside start
    second = tmp_path / "second"
    other = subprocess.run(["bash", SCRIPT, "start", str(second), *pinned[:4], "--restore", str(saved)],
                           capture_output=True, text=True)  # fmt: skip
    assert other.returncode == 2 and "is another run's" in other.stderr and not second.exists()
    shutil.copytree(saved, tmp_path / "bare", ignore=shutil.ignore_patterns("carry"))
    bare = subprocess.run(["bash", SCRIPT, "start", str(second), *pinned, "--restore", str(tmp_path / "bare")],
                          capture_output=True, text=True)  # fmt: skip
    assert bare.returncode == 2 and "carries nothing" in bare.stderr and not second.exists()
    resume = ["bash", SCRIPT, "resume", str(second), "--restore", str(saved)]
    resumed = subprocess.run(resume, capture_output=True, text=True)
    assert resumed.returncode == 2 and "--restore is for start" in resumed.stderr

    out = run_tool(["bash", SCRIPT, "start", str(second), *pinned, "--restore", str(saved), "--foreground"], tmp_path)
    assert f"restored from {saved}: models/.resume (" in out
    log = (second / "long_run.log").read_text()
    # neither seed starts again: the finished one from its last step, the stopped one from where it stopped
    assert "resuming training from step 600 " in log and f"resuming training from step {stopped} " in log

    # a finished stage's outputs carried: DVC skips it on the next machine, and what follows scores the same
    again = tmp_path / "again"
    phase0 = f"models/{MAZE}/phase0"
    run_tool(["bash", SCRIPT, "save", str(second), "--into", str(again), "--carry", phase0], tmp_path)
    third = tmp_path / "third"
    out = run_tool(["bash", SCRIPT, "start", str(third), *pinned, "--restore", str(again), "--foreground"], tmp_path)
    assert f"in DVC's cache: {phase0} (pretrain@{MAZE})" in out
    log = (third / "long_run.log").read_text()
    assert f"Running stage 'collect@{MAZE}'" in log and f"Running stage 'pretrain@{MAZE}'" not in log
    assert f"Running stage 'evaluate-phase0@{MAZE}'" in log
    unseen = f"metrics/tasks/{MAZE}/phase0-unseen.json"
    assert (third / unseen).read_bytes() == (second / unseen).read_bytes()


def _wait_for(condition: Callable[[], bool], folder: Path, timeout_s: float = 600.0) -> None:
    """Poll ``condition`` until it holds; fail with the run's log after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, (folder / "long_run.log").read_text()
        time.sleep(0.2)


def _state_step(path: Path) -> int:
    """The step of the resume state at ``path``, or -1 where there is none (yet, or any more)."""
    try:
        return torch.load(path, weights_only=False)["step"]
    except FileNotFoundError:
        return -1


def _maze_phases_only(path: Path) -> None:
    """The smoke profile's first evolution phase on the maze task alone (with its control), in episodes of two plans."""
    raw = yaml.safe_load(path.read_text())
    raw.update(tasks=[MAZE], collect_tasks=[MAZE], unseen_tasks=[MAZE], evolve=MAZE, phases={"phase1": {"previous": 0}})
    raw["task"][MAZE]["env"] = {"episode_steps": 2 * raw["diffusion"]["horizon"]}
    raw["evolution"]["generate"] |= {"replan_every": raw["diffusion"]["horizon"]}
    path.write_text(yaml.safe_dump(raw, sort_keys=False))


@pytest.mark.e2e
def test_science_maze_runs_both_recipes_on_one_phase0_and_continues_after_a_stop_or_on_a_new_machine(
    tmp_path: Path,
) -> None:
    (tmp_path / "project").mkdir()
    project = make_smoke_project(tmp_path / "project", run_tool, edit=_maze_phases_only)
    (project / "scripts").mkdir()
    shutil.copy2(REPO / "scripts" / "science_maze.sh", project / "scripts")
    run_tool(["git", "add", "scripts"], project)
    run_tool(["git", "commit", "-qm", "science_maze.sh"], project)
    head = run_tool(["git", "rev-parse", "HEAD"], project).strip()
    pinned = ["--from", str(project), "--commit", head, "--script", "scripts/science_maze.sh", "--venv", sys.prefix]
    first = tmp_path / "first"
    run_tool(["bash", SCRIPT, "start", str(first), *pinned, "--foreground"], tmp_path)
    log = (first / "long_run.log").read_text()

    plans, rollouts = log.split("evolution.generate.recipe=rollouts", 1)
    for stage in ("collect", "pretrain", "evaluate-phase0"):
        assert f"Running stage '{stage}@{MAZE}'" in plans and f"Stage '{stage}@{MAZE}' didn't change" in rollouts
    # phase 1's control is trained once (phase k's starts from phase k-1's model: that recipe's own)
    assert "Running stage 'control@phase1'" in plans and "Running stage 'control@phase1'" not in rollouts
    for stage in ("generate@phase1", "discriminate@phase1", "finetune@phase1"):
        assert f"Running stage '{stage}'" in plans and f"Running stage '{stage}'" in rollouts

    science = first / "metrics" / "science"
    read = lambda run, name: json.loads((run / "metrics" / "science" / f"{name}.json").read_text())  # noqa: E731
    first_pass, second_pass = read(first, MAZE)[MAZE], read(first, f"{MAZE}-rollouts")[MAZE]
    assert first_pass["phase_0"] == second_pass["phase_0"]  # one phase 0 and one control, scored on the same episodes
    assert first_pass["phase_1"]["control"]["score_mean"] == second_pass["phase_1"]["control"]["score_mean"]
    raw = yaml.safe_load((first / "params.yaml").read_text())
    assert raw["evolution"]["generate"]["recipe"] == "plans"
    for name, summary in ((MAZE, first_pass), (f"{MAZE}-rollouts", second_pass)):
        assert summary_of(raw, science / name)[MAZE] == summary  # each pass's per-seed metrics, kept beside it
        assert [path.name for path in (science / name).iterdir()] == raw["tasks"]  # of the tasks it ran only

    # run again (as after a stop): a pass whose summary this run wrote is not run again
    again = run_tool(["bash", "scripts/science_maze.sh"], first)
    for recipe, name in (("plans", MAZE), ("rollouts", f"{MAZE}-rollouts")):
        assert f"the {recipe} pass is done (metrics/science/{name}.json, this run's): not run again" in again
    assert "Running stage" not in again and "recipe=" not in again
    # a pass whose record is not whole, or was made with other params, runs again: DVC's run cache restores the
    # models of each recipe, and the uncached evaluations that rerun give the same summaries
    shutil.rmtree(science / f"{MAZE}-rollouts")
    with (science / f"{MAZE}.params.yaml").open("a") as params_record:
        params_record.write("# another setting\n")
    again = run_tool(["bash", "scripts/science_maze.sh"], first)
    for recipe in ("plans", "rollouts"):
        assert f"evolution.generate.recipe={recipe}" in again and f"the {recipe} pass is done" not in again
    assert not any(f"Running stage '{stage}@" in again for stage in ("collect", "pretrain", "finetune", "control"))
    assert read(first, MAZE)[MAZE] == first_pass and read(first, f"{MAZE}-rollouts")[MAZE] == second_pass
    assert (science / f"{MAZE}.params.yaml").read_text() == (first / "params.yaml").read_text()

    # the machine gone during the rollouts pass: a save with its lock, the plans pass's record and the models both
    # passes share (phase 0, phase 1's control) continues on a new clone with the rollouts pass alone
    record = f"metrics/science/{MAZE}"
    carry = [
        record + ".json",
        record,
        record + ".params.yaml",
        f"models/{MAZE}/phase0",
        f"models/{MAZE}/phase1-control",
    ]
    saved = tmp_path / "saved"
    carried = [arg for path in carry for arg in ("--carry", path)]
    run_tool(["bash", SCRIPT, "save", str(first), "--into", str(saved), *carried], tmp_path)
    second = tmp_path / "second"
    run_tool(["bash", SCRIPT, "start", str(second), *pinned, "--restore", str(saved), "--foreground"], tmp_path)
    log = (second / "long_run.log").read_text()
    assert "the plans pass is done" in log and "evolution.generate.recipe=plans" not in log
    assert log.count("Running stage 'finetune@phase1'") == 1  # the rollouts pass's, whose model was not carried
    assert "Running stage 'pretrain@" not in log and "Running stage 'control@phase1'" not in log
    assert read(second, f"{MAZE}-rollouts") == read(first, f"{MAZE}-rollouts")  # the uninterrupted run's figures


@pytest.mark.e2e
def test_science_locomotion_evolves_each_task_on_one_phase0(tmp_path: Path) -> None:
    """scripts/science_locomotion.sh on the science-locomotion profile at tiny scale (HalfCheetah left out: its
    1000-step evaluation episodes take most of the time, and it only ever runs phase 0): Walker2d's phases, then
    Hopper's, on the phase 0 the first run computed for every task."""

    def without_halfcheetah(path: Path) -> None:
        raw = yaml.safe_load(path.read_text())
        for key in ("tasks", "collect_tasks"):
            raw[key] = [task for task in raw[key] if task != "halfcheetah-medium"]
        path.write_text(yaml.safe_dump(raw, sort_keys=False))

    project = make_smoke_project(tmp_path, run_tool, edit=without_halfcheetah, profile="science-locomotion", tiny=True)
    (project / "scripts").mkdir()
    shutil.copy2(REPO / "scripts" / "science_locomotion.sh", project / "scripts")
    log = run_tool(["bash", "scripts/science_locomotion.sh"], project)

    walker_run, hopper_run = log.split("evolve=hopper-medium", 1)
    for task in ("hopper-medium", "walker2d-medium"):
        assert f"Running stage 'pretrain@{task}'" in walker_run and f"Running stage 'pretrain@{task}'" not in hopper_run
    for stage in ("generate@phase1", "finetune@phase1", "control@phase1"):
        assert f"Running stage '{stage}'" in walker_run and f"Running stage '{stage}'" in hopper_run
    science = project / "metrics" / "science"
    walker = json.loads((science / "walker2d-medium.json").read_text())
    hopper = json.loads((science / "hopper-medium.json").read_text())
    cheetah = json.loads((science / "halfcheetah-medium.json").read_text())
    assert "phase_1" in walker["walker2d-medium"] and "phase_1" not in walker["hopper-medium"]
    assert "phase_1" in hopper["hopper-medium"] and "phase_1" not in hopper["walker2d-medium"]
    assert walker["hopper-medium"]["phase_0"] == hopper["hopper-medium"]["phase_0"]  # one phase 0
    assert cheetah == hopper  # the last summary: every task's phase 0
    assert yaml.safe_load((project / "params.yaml").read_text())["evolve"] == "walker2d-medium"


def test_stop_ends_the_run_and_everything_it_started(tmp_path: Path) -> None:
    repo = tmp_path / "repo"
    repo.mkdir()
    # a run with a child process, as DVC starts its stages, that takes a while to go when told to (as a training
    # stage ends its step and writes its resume state): stop waits for it. It says when its trap is set: a TERM
    # before that would end it at once (the race CI once lost when the test paused the run too early)
    child = "trap 'sleep 2; echo saved > saved.txt; exit 143' TERM; echo > trapped.txt; while true; do sleep 0.1; done"
    (repo / "work.sh").write_text(f"( {child} ) &\nwait\n")
    for cmd in (["git", "init", "-q"], ["git", "add", "work.sh"]):
        run_tool(cmd, repo)
    run_tool(["git", "-c", "user.email=t@example.com", "-c", "user.name=t", "commit", "-qm", "work"], repo)
    folder = tmp_path / "run"
    run_tool(["bash", SCRIPT, "start", str(folder), "--from", str(repo), "--script", "work.sh", "--venv", sys.prefix],
             tmp_path)  # fmt: skip
    pid = int((folder / "long_run.pid").read_text())
    deadline = time.monotonic() + 60
    while len(_group(pid)) < 2 or not (folder / "trapped.txt").exists():  # the script and its child, trap set
        assert time.monotonic() < deadline, _group(pid)
        time.sleep(0.1)

    os.killpg(pid, signal.SIGSTOP)  # paused, as to lend the CPU for a while: stop wakes it to take the TERM
    out = run_tool(["bash", SCRIPT, "stop", str(folder)], tmp_path)
    assert f"stopped {folder}" in out and "long_run.sh resume" in out
    assert _group(pid) == []  # the script and its child are gone
    assert (folder / "saved.txt").read_text() == "saved\n"  # the child was let finish
    again = subprocess.run(["bash", SCRIPT, "stop", str(folder)], capture_output=True, text=True)
    assert again.returncode == 2 and "is not running" in again.stderr

    # save replaces an earlier save of this run, never another run's measurements (nor a folder that is no save)
    ours = tmp_path / "ours"
    run_tool(["bash", SCRIPT, "save", str(folder), "--into", str(ours)], tmp_path)
    run_tool(["bash", SCRIPT, "save", str(folder), "--into", str(ours)], tmp_path)
    theirs, not_a_save = tmp_path / "theirs", tmp_path / "not-a-save"
    theirs.mkdir()
    (theirs / "run.json").write_text(json.dumps({"commit": "0" * 40, "profile": ""}))
    not_a_save.mkdir()
    (not_a_save / "notes.txt").write_text("mine\n")
    for dest in (theirs, not_a_save):
        before = {path.name: path.read_text() for path in dest.iterdir()}
        save = ["bash", SCRIPT, "save", str(folder), "--into", str(dest)]
        refused = subprocess.run(save, capture_output=True, text=True)
        assert refused.returncode == 2 and "holds other measurements" in refused.stderr
        assert {path.name: path.read_text() for path in dest.iterdir()} == before  # untouched


def _group(pgid: int) -> list[str]:
    """The live (not zombie) processes of process group ``pgid``, read from /proc."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()  # after "pid (comm)": state, ppid, pgrp, ...
        except OSError:  # the process ended while we looked
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            members.append(stat.parent.name)
    return members


def test_a_run_after_another_starts_when_that_one_has_finished_and_not_when_it_was_stopped(tmp_path: Path) -> None:
    repo = tmp_path / "repo"
    repo.mkdir()
    (repo / "slow.sh").write_text("sleep ${SLOW_S:-2}; date +%s.%N > ended.txt\n")
    (repo / "mark.sh").write_text("date +%s.%N > started.txt\n")
    for cmd in (["git", "init", "-q"], ["git", "add", "slow.sh", "mark.sh"]):
        run_tool(cmd, repo)
    run_tool(["git", "-c", "user.email=t@example.com", "-c", "user.name=t", "commit", "-qm", "work"], repo)
    env = os.environ | {"LONG_RUN_POLL_S": "0.2"}

    def long_run(*args: str, **extra: str) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", SCRIPT, *args], capture_output=True, text=True, env=env | extra, cwd=tmp_path)

    def start(name: str, script: str, *after: str, **extra: str) -> subprocess.CompletedProcess:
        venv = ["--venv", sys.prefix]
        return long_run("start", str(tmp_path / name), "--from", str(repo), "--script", script, *venv, *after, **extra)

    first, then = tmp_path / "first", tmp_path / "then"
    assert start("first", "slow.sh").returncode == 0
    queued = start("then", "mark.sh", "--after", str(first))
    assert queued.returncode == 0 and "waiting in the background" in queued.stdout, queued.stderr
    assert (then / "long_run.after").read_text().strip() == str(first)
    assert not (then / "started.txt").exists()  # first still runs
    _wait_for(lambda: (then / "long_run.rc").exists(), then)
    assert (first / "long_run.rc").read_text() == "0\n" and (then / "long_run.rc").read_text() == "0\n"
    assert float((then / "started.txt").read_text()) >= float((first / "ended.txt").read_text())
    assert not (then / "long_run.after").exists()
    after_finished = start("at-once", "mark.sh", "--after", str(first))  # a finished run: this one runs at once
    assert "running in the background" in after_finished.stdout, after_finished.stderr

    stopped, waiting = tmp_path / "stopped", tmp_path / "waiting"
    assert start("stopped", "slow.sh", SLOW_S="60").returncode == 0
    assert start("waiting", "mark.sh", "--after", str(stopped)).returncode == 0
    assert long_run("stop", str(stopped)).returncode == 0
    _wait_for(lambda: "not started:" in (waiting / "long_run.log").read_text(), waiting)
    assert not (waiting / "started.txt").exists() and not (stopped / "long_run.rc").exists()
    refused = start("never", "mark.sh", "--after", str(stopped))  # neither runs nor finished: refused, nothing made
    assert refused.returncode == 2 and "neither runs nor has finished" in refused.stderr
    assert not (tmp_path / "never").exists()
    assert long_run("resume", str(waiting)).returncode == 0  # the queued run starts by hand
    _wait_for(lambda: (waiting / "started.txt").exists(), waiting)
