"""A temporary git + DVC repository holding this project on the smoke profile, as the end-to-end tests use it."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
PROJECT_FILES = ["dvc.yaml", "params.yaml", "pipeline", "profiles", "src", ".dvcignore", ".gitignore"]


def traces_dir(root: Path) -> Path:
    """Where the shared smoke repro (the ``smoke_repo`` fixture) of the project at ``root`` writes its stage traces
    (tests/deps_trace.py): a sibling folder, so that nothing is written into the project, DVC's files included."""
    return root.parent / f"{root.name}-deps-trace"


def make_smoke_project(
    root: Path,
    run: Callable[[list[str], Path], object],
    edit: Callable[[Path], None] | None = None,
    profile: str = "smoke",
    tiny: bool = False,
) -> Path:
    """Copy the project into ``root``, make it a git + DVC repository on the smoke profile (or ``profile``, at tiny
    scale with ``tiny``; ``edit(params_path)`` may change the params first) and commit it; ``run(cmd, cwd)`` runs
    each command and fails the test on error."""
    for name in PROJECT_FILES:
        src = REPO / name
        if src.is_dir():
            shutil.copytree(src, root / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            shutil.copy2(src, root / name)
    run(["git", "init", "-q"], root)
    run(["git", "config", "user.email", "test@example.com"], root)
    run(["git", "config", "user.name", "test"], root)
    run(["dvc", "init", "-q"], root)
    run(["adaptdiffuser", "profile", profile, *(["--tiny"] if tiny else [])], root)
    if edit is not None:
        edit(root / "params.yaml")
    run(["git", "add", "-A"], root)
    run(["git", "commit", "-qm", "smoke project"], root)
    return root


def narrow(raw: dict, tasks: list[str], **keys: object) -> dict:
    """Params ``raw`` (a profile's) running ``tasks`` alone, in the order given (as its ``tasks``, ``collect_tasks``
    and ``pretrain_tasks``), then the top-level ``keys`` (``evolve``, ``phases``, ``unseen_tasks``, ``seeds``, ...)
    set as given: a key named there (``pretrain_tasks=[]``) wins."""
    unknown = sorted(set(tasks) - set(raw["task"]))
    assert not unknown, f"{unknown}: the profile has no settings for them"
    return {**raw, "tasks": list(tasks), "collect_tasks": list(tasks), "pretrain_tasks": list(tasks), **keys}


def only_tasks(tasks: list[str], **keys: object) -> Callable[[Path], None]:
    """A params edit for :func:`make_smoke_project`: the project runs ``tasks`` alone, in the profile's order (its
    pipeline lists only the profile's tasks), as :func:`narrow` sets them."""

    def edit(path: Path) -> None:
        raw = yaml.safe_load(path.read_text())
        unknown = sorted(set(tasks) - set(raw["tasks"]))
        assert not unknown, f"{unknown}: not tasks of the profile"
        kept = [task for task in raw["tasks"] if task in tasks]
        path.write_text(yaml.safe_dump(narrow(raw, kept, **keys), sort_keys=False))

    return edit


def tool_env() -> dict[str, str]:
    """The environment the command-line tools (dvc, git, adaptdiffuser) run in: this interpreter's scripts first on
    the PATH, the project's own MLflow store (no inherited ``MLFLOW_TRACKING_URI``), no DVC analytics."""
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env['PATH']}"
    env.pop("MLFLOW_TRACKING_URI", None)
    env["DVC_NO_ANALYTICS"] = "1"
    return env


def run_tool(cmd: list[str], cwd: Path, **env: str) -> str:
    """Run ``cmd`` in ``cwd`` (extra environment ``env``), fail the test with its output on a non-zero exit, and
    return its stdout and stderr."""
    out = subprocess.run(cmd, cwd=cwd, env=tool_env() | env, capture_output=True, text=True)
    assert out.returncode == 0, f"{' '.join(cmd)} failed:\n{out.stdout}\n{out.stderr}"
    return out.stdout + out.stderr


def run_queue(root: Path, workers: int = 2, timeout_s: float = 1500.0) -> str:
    """Run the DVC experiments queued in ``root`` on ``workers`` workers (one torch thread each) until none is
    queued or running; return the last ``dvc queue status`` table. Each poll is a `dvc` process (about a CPU-second)
    taken from the experiments on the same cores, so the wait between polls grows from 5 s to 30 s."""
    run_tool(["dvc", "queue", "start", "-j", str(workers)], root, OMP_NUM_THREADS="1")
    try:
        deadline = time.monotonic() + timeout_s
        wait = 5.0
        while True:
            status = run_tool(["dvc", "queue", "status"], root)
            if not re.search(r"\b(Queued|Running)\b", status):
                return status
            assert time.monotonic() < deadline, f"the queue did not finish in {timeout_s:.0f} s:\n{status}"
            time.sleep(wait)
            wait = min(1.5 * wait, 30.0)
    finally:
        run_tool(["dvc", "queue", "stop"], root)
