"""A set of params values as a DVC experiment (``dvc exp run``), as the sweep records its best trial.

``run`` reproduces the pipeline with the values in a temporary copy of the repository (``dvc exp run --temp``:
the workspace and its ``params.yaml`` are left as they are) and saves the result as a named experiment that
``dvc exp show`` compares with the others; ``queue`` only stages it (``dvc exp run --queue``) for a later
``dvc queue start``. Either needs a git repository with a commit and DVC initialized, checked before any work.
"""

from __future__ import annotations

import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import yaml

from adaptdiffuser.errors import StageError

#: how a sweep records its best trial: run it now, queue it, or not at all
ExperimentMode = Literal["run", "queue", "none"]
EXPERIMENT_MODES: tuple[str, ...] = ("run", "queue", "none")


def set_param_args(values: Mapping[str, Any]) -> list[str]:
    """``-S key=value`` arguments of ``dvc exp run`` for ``values`` (each value as a YAML flow scalar)."""
    args: list[str] = []
    for key, value in values.items():
        text = yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("\n...").strip()
        args += ["-S", f"{key}={text}"]
    return args


def check_experiment_repo(root: Path) -> None:
    """Refuse, before any work, a project where ``dvc exp run`` cannot record an experiment."""
    if not (root / ".dvc").is_dir():
        raise StageError(f"{root}: not a DVC repository (no .dvc folder); run `dvc init` or use --dvc-exp none")
    head = subprocess.run(["git", "rev-parse", "--verify", "HEAD"], cwd=root, capture_output=True, text=True)
    if head.returncode != 0:
        raise StageError(
            f"{root}: DVC experiments need a git repository with at least one commit; commit or use --dvc-exp none"
        )


def record_experiment(
    root: Path, name: str, values: Mapping[str, Any], mode: ExperimentMode, message: str = ""
) -> subprocess.CompletedProcess[str]:
    """Run (``mode='run'``, in a temporary copy) or queue (``'queue'``) the pipeline of ``root`` with ``values`` as
    the DVC experiment ``name``; a failure raises :class:`StageError` with DVC's own message."""
    if mode not in ("run", "queue"):
        raise ValueError(f"record_experiment: mode must be 'run' or 'queue', got {mode!r}")
    cmd = ["dvc", "exp", "run", "--temp" if mode == "run" else "--queue", "-n", name, *set_param_args(values)]
    if message:
        cmd += ["-m", message]
    out = subprocess.run(cmd, cwd=root, capture_output=True, text=True)
    if out.returncode != 0:
        tail = "\n".join((out.stdout + out.stderr).strip().splitlines()[-15:])
        raise StageError(f"`{' '.join(cmd)}` failed (exit {out.returncode}):\n{tail}")
    return out
