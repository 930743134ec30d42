"""`adaptdiffuser run start|status|stop`: a long run in the background of a DVC project, stopped or killed part-way
and continued by starting it again (DVC skips what finished, training resumes from models/.resume/), on the same
machine or, with its resume states and DVC's run cache carried, on another."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
import yaml
from smoke_project import REPO, make_smoke_project, only_tasks, run_tool, tool_env

from adaptdiffuser.stages.pool import summary_of
from adaptdiffuser.tooling.long_run import log_path, running_record, start, status, stop

MAZE = "maze2d-umaze"
STEPS, EVERY = 400, 50  # pretraining steps and steps between checkpoints: 20-30 s a seed on a busy 2-core machine


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``adaptdiffuser run ARGS`` in ``cwd``, whatever its exit status."""
    return subprocess.run(["adaptdiffuser", "run", *args], cwd=cwd, env=tool_env(), capture_output=True, text=True)


def _pgid(root: Path) -> int:
    """The process group of the run's command, from the run's record."""
    return json.loads((root / ".long-run" / "run.json").read_text())["pgid"]


def _gone(pid: int) -> bool:
    """Whether process ``pid`` is gone and reaped (a zombie keeps its /proc entry, and DVC takes it for alive)."""
    return not Path(f"/proc/{pid}").exists()


def _wait_for(condition: Callable[[], bool], root: Path, timeout_s: float = 600.0) -> None:
    """Poll ``condition`` until it holds; fail with the run's log after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, log_path(root).read_text() if log_path(root).exists() else "no log"
        time.sleep(0.1)


def _ended(root: Path) -> bool:
    """Whether the run of ``root`` has ended: its supervisor has reaped every process of it and gone."""
    return running_record(root) is None


def _bare_project(root: Path) -> Path:
    root.mkdir()
    for cmd in (["git", "init", "-q"], ["dvc", "init", "-q"]):
        run_tool(cmd, root)
    run_tool(["git", "-c", "user.email=t@example.com", "-c", "user.name=t", "commit", "-qm", "dvc"], root)
    return root


def _dvc_files(root: Path) -> dict[str, bytes]:
    """Every file under ``.dvc/`` with its content."""
    return {str(path.relative_to(root)): path.read_bytes() for path in (root / ".dvc").rglob("*") if path.is_file()}


def test_stop_ends_the_run_and_everything_it_started(tmp_path: Path) -> None:
    root = _bare_project(tmp_path / "repo")
    dvc_before = _dvc_files(root)
    # a child process, as DVC starts its stages, that takes a while to go when told to (as a training stage ends its
    # step and writes its resume state): stop waits for it. Its pid is written once its trap is set (a TERM before
    # would end it), and the script writes its own
    child = "trap 'sleep 1; echo saved > saved.txt; exit 143' TERM; echo $BASHPID > child.pid; "
    child += "while :; do sleep 1; done"
    (root / "work.sh").write_text(f"echo $$ > script.pid\n( {child} ) &\nwait\n")
    out = run_tool(["adaptdiffuser", "run", "start", "--", "bash", "work.sh"], root)
    assert "running in the background" in out
    pgid = _pgid(root)
    _wait_for(lambda: (root / "child.pid").exists() and (root / "script.pid").exists(), root)
    pids = [int((root / name).read_text()) for name in ("script.pid", "child.pid")]
    refused = _run("start", cwd=root)
    assert refused.returncode == 2 and f"already runs (pid {pgid})" in refused.stderr
    assert f"running: pid {pgid}" in _run("status", cwd=root).stdout

    os.killpg(pgid, signal.SIGSTOP)  # paused, as to lend the CPU for a while: stop wakes it to take the TERM
    out = run_tool(["adaptdiffuser", "run", "stop"], root)
    assert out.startswith("stopped;") and "adaptdiffuser run start" in out
    assert all(_gone(pid) for pid in pids)  # the script and its child are gone, and reaped: no zombie is left
    assert (root / "saved.txt").read_text() == "saved\n"  # the child was let finish
    assert _dvc_files(root) == dvc_before  # nothing of a start and a stop is written under .dvc/ (no rwlock)
    again = _run("stop", cwd=root)
    assert again.returncode == 2 and "does not run" in again.stderr
    said = _run("status", cwd=root).stdout
    assert "stopped or killed (by adaptdiffuser run stop, SIGTERM)" in said
    assert "dvc status: every stage is up to date" in said

    # the same in this process, as the command line is a thin layer over it: a child that ignores the TERM is killed
    # after the grace period
    (root / "stubborn.sh").write_text("trap '' TERM; echo $$ > stubborn.pid; while :; do sleep 1; done\n")
    start(root, ["bash", "stubborn.sh"])
    _wait_for((root / "stubborn.pid").exists, root)
    assert stop(root, grace_s=1) is True  # SIGKILL was needed
    assert _gone(int((root / "stubborn.pid").read_text()))

    # a run that ends by itself says how; one that cannot start is refused
    start(root, ["sh", "-c", "printf 'a progress bar'; exit 3"])  # how it ended goes on a line of its own
    _wait_for(lambda: _ended(root), root)
    assert status(root)[0] == f"failed: exit status 3 (see {log_path(root)}); continue: adaptdiffuser run start"
    start(root, ["true"])
    _wait_for(lambda: _ended(root), root)
    refused = _run("start", "--", "no-such-command-here", cwd=root)
    assert refused.returncode == 2 and "cannot start no-such-command-here" in refused.stderr
    ends = re.findall(r"^== \S+ (\w+) \(exit status", log_path(root).read_text(), re.MULTILINE)
    assert ends == ["stopped", "stopped", "failed", "finished"]  # every start appends to one log, and how it ended
    git_status = run_tool(["git", "status", "--porcelain", "--untracked-files=all"], root)
    assert (root / ".long-run" / "run.json").exists() and ".long-run" not in git_status  # the folder ignores itself

    refused = _run("status", cwd=tmp_path)
    assert refused.returncode == 2 and "is not a DVC project" in refused.stderr


def test_a_stopped_dvc_repro_leaves_no_zombie_holding_dvcs_lock(tmp_path: Path) -> None:
    """DVC records its pid in ``.dvc/tmp/rwlock`` while a stage runs; a stop ends it there, and the entry stays. DVC
    ignores entries of processes that are gone, and the run reaps them, so the next ``dvc repro`` goes on, with
    nothing of ours editing DVC's file."""
    root = _bare_project(tmp_path / "repo")
    script = "import pathlib as p, time; p.Path('started').touch(); time.sleep(0 if p.Path('quick').exists() else 300)"
    stage = {"cmd": f'python -c "{script}" && echo done > out.txt', "outs": ["out.txt"]}
    (root / "dvc.yaml").write_text(yaml.safe_dump({"stages": {"slow": stage}}))
    run_tool(["git", "add", "dvc.yaml"], root)
    run_tool(["git", "-c", "user.email=t@example.com", "-c", "user.name=t", "commit", "-qm", "slow"], root)
    run_tool(["adaptdiffuser", "run", "start"], root)  # dvc repro
    _wait_for((root / "started").exists, root, timeout_s=120)
    rwlock = root / ".dvc" / "tmp" / "rwlock"
    dvc_pid = json.loads(rwlock.read_text())["write"][str((root / "out.txt").resolve())]["pid"]
    assert dvc_pid == _pgid(root)  # the run's command is DVC itself

    assert run_tool(["adaptdiffuser", "run", "stop", "--grace", "20"], root).startswith("stopped;")
    assert str(dvc_pid) in rwlock.read_text() and _gone(dvc_pid)  # DVC's entry is left, its process reaped
    assert "dvc status: 1 stages to run (slow)" in run_tool(["adaptdiffuser", "run", "status"], root)

    (root / "quick").touch()
    run_tool(["adaptdiffuser", "run", "start"], root)  # not refused by DVC: the lock's holder is gone
    _wait_for(lambda: _ended(root), root, timeout_s=120)
    assert status(root)[:2] == ["finished: ended by itself with exit status 0", "dvc status: every stage is up to date"]
    assert (root / "out.txt").read_text() == "done\n"


def _phase0_of_one_task(path: Path) -> None:
    """Phase 0 of the maze task alone over two training seeds, with a pretraining long enough to be stopped between
    its checkpoints, ``EVERY`` steps apart."""
    only_tasks([MAZE], unseen_tasks=[MAZE], evolve=None, phases={}, seeds=[0, 1])(path)
    raw = yaml.safe_load(path.read_text())
    raw["pretrain"] |= {"steps": STEPS, "checkpoint_every": EVERY}
    path.write_text(yaml.safe_dump(raw, sort_keys=False))


def _state_step(path: Path) -> int:
    """The step of the resume state at ``path``, or -1 where there is none (yet, or any more)."""
    try:
        return torch.load(path, weights_only=False)["step"]
    except (FileNotFoundError, EOFError, RuntimeError):
        return -1


@pytest.mark.e2e
def test_a_stopped_run_continues_on_another_machine_and_a_killed_one_where_it_is(tmp_path: Path) -> None:
    (tmp_path / "first").mkdir()
    first = make_smoke_project(tmp_path / "first", run_tool, edit=_phase0_of_one_task)
    resume = Path("models") / ".resume"
    seed1 = resume / f"{MAZE}-phase0-seed1.pt"
    run_tool(["adaptdiffuser", "run", "start"], first)
    # stopped once the second seed's pretraining has written a whole resume state (the first seed's is finished):
    # SIGTERM to the run's process group, and the stage ends its step and writes its state there before it goes
    _wait_for((first / seed1).exists, first)
    stop(first)  # in this process: no interpreter start between the first checkpoint and the stop
    stops = re.findall(r"SIGTERM: stopping after step (\d+),", log_path(first).read_text())
    assert len(stops) == 1, log_path(first).read_text()  # seed 1's pretraining took the stop
    stopped = int(stops[0])
    said = run_tool(["adaptdiffuser", "run", "status"], first)
    assert "stopped or killed" in said and f"pretrain@{MAZE}" in said  # dvc status: pretraining is left
    assert f"resume state: {MAZE}-phase0-seed0.pt (step {STEPS})" in said  # finished, kept until the stage ends
    assert f"resume state: {MAZE}-phase0-seed1.pt (step {stopped})" in said

    # the machine goes: what continues the run exactly is its resume states and DVC's run cache of the stages that
    # finished (on a remote, which `dvc repro --pull` reads), on a clone of the same commit
    remote = tmp_path / "remote"
    run_tool(["dvc", "remote", "add", "--local", "shared", str(remote)], first)
    run_tool(["dvc", "push", "--run-cache", "-r", "shared"], first)
    second = tmp_path / "second"
    run_tool(["git", "clone", "-q", str(first), str(second)], tmp_path)
    shutil.copytree(first / resume, second / resume)
    run_tool(["dvc", "remote", "add", "--local", "--default", "shared", str(remote)], second)

    run_tool(["adaptdiffuser", "run", "start", "--", "dvc", "repro", "--pull"], second)
    # then killed outright (SIGKILL, as when the machine goes) once the resumed training has passed a checkpoint
    _wait_for(lambda: _state_step(second / seed1) > stopped, second)
    dvc_pid = _pgid(second)
    os.killpg(dvc_pid, signal.SIGKILL)  # DVC and its stage; the run's supervisor reaps them
    _wait_for(lambda: _ended(second), second)
    assert _gone(dvc_pid) and "stopped or killed (by SIGKILL)" in run_tool(["adaptdiffuser", "run", "status"], second)
    run_tool(["adaptdiffuser", "run", "start"], second)  # the same command continues it
    _wait_for(lambda: _ended(second), second)

    log = log_path(second).read_text()
    assert f"Stage 'collect@{MAZE}' is cached - skipping run" in log  # the data from the run cache, not collected
    # the first seed is not trained again, the second goes on from its checkpoints, never from step 0
    assert f"resuming training from step {STEPS} " in log and f"resuming training from step {stopped} " in log
    assert any(f"resuming training from step {step} " in log for step in range(EVERY, STEPS, EVERY) if step > stopped)
    said = run_tool(["adaptdiffuser", "run", "status"], second)
    assert "finished: ended by itself with exit status 0" in said, said
    assert "every stage is up to date" in said and "resume state:" not in said
    assert (second / f"metrics/tasks/{MAZE}/phase0-unseen.json").exists()


def _maze_phases_only(path: Path) -> None:
    """The smoke profile's first evolution phase on the maze task alone (with its control), in episodes of two plans."""
    only_tasks([MAZE], unseen_tasks=[MAZE], evolve=MAZE, phases={"phase1": {"previous": 0}})(path)
    raw = yaml.safe_load(path.read_text())
    raw["task"][MAZE]["env"] = {"episode_steps": 2 * raw["diffusion"]["horizon"]}
    raw["evolution"]["generate"] |= {"replan_every": raw["diffusion"]["horizon"]}
    path.write_text(yaml.safe_dump(raw, sort_keys=False))


@pytest.mark.e2e
def test_science_maze_runs_both_recipes_on_one_phase0_and_continues_after_a_stop(tmp_path: Path) -> None:
    (tmp_path / "project").mkdir()
    project = make_smoke_project(tmp_path / "project", run_tool, edit=_maze_phases_only)
    (project / "scripts").mkdir()
    shutil.copy2(REPO / "scripts" / "science_maze.sh", project / "scripts")
    run_tool(["git", "add", "scripts"], project)
    run_tool(["git", "commit", "-qm", "science_maze.sh"], project)
    log = run_tool(["bash", "scripts/science_maze.sh"], project)

    plans, rollouts = log.split("evolution.generate.recipe=rollouts", 1)
    for stage in ("collect", "pretrain", "evaluate-phase0"):
        assert f"Running stage '{stage}@{MAZE}'" in plans and f"Stage '{stage}@{MAZE}' didn't change" in rollouts
    # phase 1's control is trained once (phase k's starts from phase k-1's model: that recipe's own)
    assert "Running stage 'control@phase1'" in plans and "Running stage 'control@phase1'" not in rollouts
    for stage in ("generate@phase1", "discriminate@phase1", "finetune@phase1"):
        assert f"Running stage '{stage}'" in plans and f"Running stage '{stage}'" in rollouts

    science = project / "metrics" / "science"
    read = lambda name: json.loads((science / f"{name}.json").read_text())  # noqa: E731
    first_pass, second_pass = read(MAZE)[MAZE], read(f"{MAZE}-rollouts")[MAZE]
    assert first_pass["phase_0"] == second_pass["phase_0"]  # one phase 0 and one control, scored on the same episodes
    assert first_pass["phase_1"]["control"]["score_mean"] == second_pass["phase_1"]["control"]["score_mean"]
    raw = yaml.safe_load((project / "params.yaml").read_text())
    assert raw["evolution"]["generate"]["recipe"] == "plans"
    for name, summary in ((MAZE, first_pass), (f"{MAZE}-rollouts", second_pass)):
        assert summary_of(raw, science / name)[MAZE] == summary  # each pass's per-seed metrics, kept beside it
        assert [path.name for path in (science / name).iterdir()] == raw["tasks"]  # of the tasks it ran only

    # run again (as after a stop): a pass whose summary this run wrote is not run again
    again = run_tool(["bash", "scripts/science_maze.sh"], project)
    for recipe, name in (("plans", MAZE), ("rollouts", f"{MAZE}-rollouts")):
        assert f"the {recipe} pass is done (metrics/science/{name}.json, this run's): not run again" in again
    assert "Running stage" not in again and "recipe=" not in again
    # a pass whose record is not whole, or was made with other params, runs again: DVC's run cache restores the
    # models of each recipe, and the uncached evaluations that rerun give the same summaries
    shutil.rmtree(science / f"{MAZE}-rollouts")
    with (science / f"{MAZE}.params.yaml").open("a") as params_record:
        params_record.write("# another setting\n")
    again = run_tool(["bash", "scripts/science_maze.sh"], project)
    for recipe in ("plans", "rollouts"):
        assert f"evolution.generate.recipe={recipe}" in again and f"the {recipe} pass is done" not in again
    assert not any(f"Running stage '{stage}@" in again for stage in ("collect", "pretrain", "finetune", "control"))
    assert read(MAZE)[MAZE] == first_pass and read(f"{MAZE}-rollouts")[MAZE] == second_pass
    assert (science / f"{MAZE}.params.yaml").read_text() == (project / "params.yaml").read_text()

    # arguments choose the passes: `plans` alone leaves the rollouts pass (its summary gone) alone; an unknown recipe
    # stops before anything runs
    (science / f"{MAZE}-rollouts.json").unlink()
    again = run_tool(["bash", "scripts/science_maze.sh", "plans"], project)
    assert "the plans pass is done" in again and "rollouts" not in again and "Running stage" not in again
    assert not (science / f"{MAZE}-rollouts.json").exists()
    wrong = subprocess.run(["bash", "scripts/science_maze.sh", "rollout"], cwd=project, capture_output=True, text=True)
    assert wrong.returncode == 2
    assert wrong.stderr.strip() == "science_maze.sh: unknown recipe 'rollout' (plans or rollouts)"


@pytest.mark.e2e
def test_science_locomotion_evolves_each_task_on_one_phase0(tmp_path: Path) -> None:
    """scripts/science_locomotion.sh on the science-locomotion profile at tiny scale (HalfCheetah left out: its
    1000-step evaluation episodes take most of the time, and it only ever runs phase 0): Walker2d's phases, then
    Hopper's, on the phase 0 the first run computed for every task."""

    no_cheetah = only_tasks(["hopper-medium", "walker2d-medium"])
    project = make_smoke_project(tmp_path, run_tool, edit=no_cheetah, profile="science-locomotion", tiny=True)
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
