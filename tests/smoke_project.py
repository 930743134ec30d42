"""A temporary git + DVC repository holding this project on the smoke profile, as the end-to-end tests use it."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PROJECT_FILES = ["dvc.yaml", "params.yaml", "pipeline", "profiles", "src", ".dvcignore", ".gitignore"]


def make_smoke_project(
    root: Path, run: Callable[[list[str], Path], object], edit: Callable[[Path], None] | None = None
) -> Path:
    """Copy the project into ``root``, make it a git + DVC repository on the smoke profile (``edit(params_path)``
    may change the params first) and commit it; ``run(cmd, cwd)`` runs each command and fails the test on error."""
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
    run(["adaptdiffuser", "profile", "smoke"], root)
    if edit is not None:
        edit(root / "params.yaml")
    run(["git", "add", "-A"], root)
    run(["git", "commit", "-qm", "smoke project"], root)
    return root
