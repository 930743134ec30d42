"""A learning curve (benchmarks/recipe_study.py, the long runs' validation curves) stopped between two of its points
keeps the training since the last point: the study lets its curve end the step and write its resume state, and the
same command continues from there with the training's clock. A longer curve of a constant learning rate extends a
shorter one to the same weights as trained from step 0, and refuses a state that is not the shorter curve's."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from smoke_project import REPO, make_smoke_project, only_tasks, run_tool, tool_env

MAZE = "maze2d-umaze"


#: phase 0 of the maze task alone
MAZE_ONLY = only_tasks([MAZE], unseen_tasks=[MAZE], evolve=None, phases={})


@pytest.mark.e2e
def test_a_stopped_curve_continues_from_the_step_it_stopped_at(tmp_path: Path) -> None:
    (tmp_path / "project").mkdir()
    project = make_smoke_project(tmp_path / "project", run_tool, edit=MAZE_ONLY)
    run_tool(["dvc", "repro", f"reference@{MAZE}"], project)
    recipes = tmp_path / "recipes.yaml"
    recipes.write_text("short: {steps: 1200}\n")
    out_dir = tmp_path / "curves"
    study = [sys.executable, str(REPO / "benchmarks" / "recipe_study.py"), str(project), "--task", MAZE,
             "--recipes", str(recipes), "--training-seeds", "0", "--every", "400", "--episodes", "2",
             "--out-dir", str(out_dir), "--quiet"]  # fmt: skip
    curve = out_dir / "short-seed0.jsonl"
    resume = project / "models" / ".resume" / f"learning-curve-{MAZE}-recipe-short-seed0.pt"
    clock = resume.with_name(f"{resume.stem}-clock.json")
    log = tmp_path / "first.log"
    with open(log, "w") as sink:  # its own process group, stopped as `adaptdiffuser run stop` stops one: SIGTERM to it
        first = subprocess.Popen(study, stdout=sink, stderr=subprocess.STDOUT, env=tool_env(), start_new_session=True)
        deadline = time.monotonic() + 600
        while _state_step(resume) != 400:  # the first point and its state are written: the stop comes after them
            assert first.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        time.sleep(1.0)  # some steps towards the next point
        os.killpg(first.pid, signal.SIGTERM)
        assert first.wait(timeout=120) == 128 + signal.SIGTERM, log.read_text()

    stops = re.findall(r"SIGTERM: stopping after step (\d+),", log.read_text())
    assert len(stops) == 1, log.read_text()  # the curve took the stop once, ended its step and wrote its state
    stopped = int(stops[0])
    assert 400 < stopped < 1200
    assert _state_step(resume) == stopped
    kept = json.loads(clock.read_text())
    point = json.loads(curve.read_text())
    assert kept["step"] == stopped and kept["train_cpu_s"] > point["train_cpu_s"]

    again = subprocess.run(study, capture_output=True, text=True, env=tool_env())
    assert again.returncode == 0, again.stdout + again.stderr
    assert f"resuming training from step {stopped} " in again.stdout + again.stderr
    points = [json.loads(line) for line in curve.read_text().splitlines()]
    assert [p["step"] for p in points] == [400, 800, 1200]
    assert points[1]["train_cpu_s"] > kept["train_cpu_s"]  # the clock went on from the stop, not from the point
    assert not resume.exists() and not clock.exists()


@pytest.mark.e2e
def test_a_longer_curve_extends_a_shorter_one_to_the_weights_of_one_trained_from_zero(tmp_path: Path) -> None:
    (tmp_path / "project").mkdir()
    project = make_smoke_project(tmp_path / "project", run_tool, edit=MAZE_ONLY)
    run_tool(["dvc", "repro", f"reference@{MAZE}"], project)
    constant = "set: {pretrain.lr_schedule: constant}"
    recipes = tmp_path / "recipes.yaml"
    recipes.write_text(f"direct: {{steps: 300, {constant}}}\nshort: {{steps: 200, {constant}}}\n"
                       f"long: {{steps: 300, {constant}, extends: short}}\n")  # fmt: skip
    out_dir = tmp_path / "curves"
    study = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "recipe_study.py"), str(project), "--task", MAZE, "--recipes",
         str(recipes), "--training-seeds", "0", "--every", "100", "--episodes", "2", "--out-dir", str(out_dir),
         "--quiet", "--only", "direct", "long"],
        capture_output=True, text=True, env=tool_env(),
    )  # fmt: skip
    assert study.returncode == 0, study.stdout + study.stderr
    assert "(200 steps) from its state at step 200" in study.stdout
    assert study.stdout.count("resuming training from step 200 ") == 1  # long, from short's state, not from 0

    def points(name: str) -> list[dict]:
        return [json.loads(line) for line in (out_dir / f"{name}-seed0.jsonl").read_text().splitlines()]

    assert [p["step"] for p in points("long")] == [100, 200, 300]
    assert points("long")[:2] == points("short")  # the shorter curve's points, trained once (--only trained it)
    states = {
        name: torch.load(
            project / "models" / ".resume" / f"learning-curve-{MAZE}-recipe-{name}-seed0.pt", weights_only=False
        )
        for name in ("direct", "short", "long")
    }  # kept: constant rate
    assert [states[name]["step"] for name in ("direct", "short", "long")] == [300, 200, 300]
    for part in ("model", "ema"):
        direct, long = states["direct"][part], states["long"][part]
        assert direct.keys() == long.keys()
        assert all(torch.equal(direct[key], long[key]) for key in direct)  # extended == trained from step 0
    assert points("long")[2]["score_mean"] == points("direct")[2]["score_mean"]

    refused = subprocess.run(  # a state of another curve (direct: 300 steps) does not extend short's points
        [sys.executable, str(REPO / "benchmarks" / "learning_curve.py"), str(project), "--task", MAZE,
         "--steps", "400", "--every", "100", "--episodes", "2", "--set", "pretrain.lr_schedule=constant",
         "--label", "other", "--out", str(tmp_path / "other.jsonl"), "--extend", str(out_dir / "short-seed0.jsonl"),
         "--extend-state", str(project / "models" / ".resume" / f"learning-curve-{MAZE}-recipe-direct-seed0.pt")],
        capture_output=True, text=True, env=tool_env(),
    )  # fmt: skip
    assert refused.returncode == 2
    assert "was not written by the curve of" in refused.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "other.jsonl").exists()


def _state_step(path: Path) -> int:
    """The step of the resume state at ``path``, or -1 where there is none (yet)."""
    try:
        return torch.load(path, weights_only=False)["step"]
    except (FileNotFoundError, EOFError, RuntimeError):  # not written yet, or being replaced
        return -1


@pytest.mark.parametrize(
    ("recipes", "message"),
    [
        ("a: {steps: 100}\nb: {steps: 200, extends: c}\n", "recipe 'b' extends 'c', not another recipe of it"),
        ("a: {steps: 100}\nb: {steps: 200, extends: b}\n", "recipe 'b' extends 'b', not another recipe of it"),
        ("a: {steps: 300}\nb: {steps: 200, extends: a}\n", "which needs the same 'set' and fewer steps"),
        ("a: {steps: 100}\nb: {steps: 200, set: {pretrain.lr: 0.001}, extends: a}\n", "needs the same 'set'"),
    ],
)
def test_a_recipe_extends_only_a_shorter_one_of_the_same_settings(tmp_path: Path, recipes: str, message: str) -> None:
    path = tmp_path / "recipes.yaml"
    path.write_text(recipes)
    study = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "recipe_study.py"), str(tmp_path), "--task", MAZE,
         "--recipes", str(path), "--out-dir", str(tmp_path / "curves")],
        capture_output=True, text=True, env=tool_env(),
    )  # fmt: skip
    assert study.returncode == 1
    assert message in study.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "curves").exists()  # refused before anything is written
