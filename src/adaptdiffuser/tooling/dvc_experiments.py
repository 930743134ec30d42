"""A set of params values as a DVC experiment (``dvc exp run``), as the sweep records its best trial.

``run`` reproduces the pipeline with the values in a temporary copy of the repository (``dvc exp run --temp``:
the workspace and its ``params.yaml`` are left as they are) and saves the result as a named experiment that
``dvc exp show`` compares with the others; ``queue`` only stages it (``dvc exp run --queue``) for a later
``dvc queue start``. Either needs a git repository with a commit and DVC initialized, checked before any work.

A multi-seed run spreads the same way: :func:`queue_seeds` queues one experiment per training seed, which
``dvc queue start -j N`` runs N at a time (``dvc exp push`` / ``pull`` carry them between machines), and
:func:`export_experiment` writes what one of them measured as a folder that ``adaptdiffuser pool`` reads.
"""

from __future__ import annotations

import json
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


def queue_seeds(root: Path, name: str, seeds: list[int]) -> list[str]:
    """Queue one experiment per training seed, ``<name>-seed<s>`` with ``seeds=[s]``; returns their names. The
    project's MLflow store is made first: workers that start together would each create it, and all but one fail."""
    check_experiment_repo(root)
    create_store(root)
    names = [f"{name}-seed{seed}" for seed in seeds]
    for seed, exp in zip(seeds, names, strict=True):
        record_experiment(root, exp, {"seeds": [seed]}, "queue", message=f"training seed {seed} of {name}")
    return names


def create_store(root: Path) -> None:
    """Create (and migrate) the project's MLflow store where it does not exist yet."""
    from mlflow import MlflowClient

    from adaptdiffuser.tooling.mlflow_logging import tracking_uri

    MlflowClient(tracking_uri(root.resolve())).search_experiments(max_results=1)


def _git(root: Path, *args: str) -> str:
    out = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True)
    if out.returncode != 0:
        last = (out.stderr.strip().splitlines() or ["no message"])[-1]
        raise StageError(f"`git {' '.join(args)}` failed: {last}")
    return out.stdout


def experiment_commit(root: Path, name: str) -> str:
    """The commit of the DVC experiment ``name`` (its name, as ``dvc exp show`` lists it, or a commit)."""
    refs = _git(root, "for-each-ref", "--format=%(refname) %(objectname)", "refs/exps/").split("\n")
    found = [line.split()[1] for line in refs if line and line.split()[0].rsplit("/", 1)[-1] == name]
    if len(found) > 1:
        raise StageError(f"experiment {name!r} is on {len(found)} baselines: name it by its commit")
    if found:
        return found[0]
    rev = subprocess.run(["git", "rev-parse", "--verify", "-q", f"{name}^{{commit}}"], cwd=root, capture_output=True)
    if rev.returncode != 0:
        raise StageError(f"no DVC experiment {name!r} in {root} (dvc exp list; dvc exp pull REMOTE {name})")
    return rev.stdout.decode().strip()


def export_experiment(root: Path, name: str, into: Path) -> str:
    """Write into ``into`` what the experiment ``name`` measured, as a run's folder: its ``params.yaml``,
    ``dvc.lock`` and the files of ``metrics/`` its stages wrote (the outs of its ``dvc.lock``) or that differ from
    its baseline commit's (what is neither, a reference, is read from the baseline), with ``run.json`` naming the
    experiment and its baseline. Returns the baseline commit."""
    commit = experiment_commit(root, name)
    baseline = _git(root, "rev-parse", f"{commit}^").strip()
    changed = _git(root, "diff", "--name-only", "--no-renames", "--diff-filter=AM", baseline, commit, "--", "metrics")
    held = _git(root, "ls-tree", "-r", "--name-only", commit, "--", "params.yaml", "dvc.lock").splitlines()
    # what the experiment's stages wrote under metrics/, even where it equals the baseline's bytes (a seed that
    # scored as the baseline's run did): the outs its dvc.lock lists
    lock = yaml.safe_load(_git(root, "show", f"{commit}:dvc.lock")) if "dvc.lock" in held else None
    outs = [
        out["path"]
        for stage in ((lock or {}).get("stages") or {}).values()
        for out in stage.get("outs", [])
        if str(out.get("path", "")).startswith("metrics/")
    ]
    written = _git(root, "ls-tree", "-r", "--name-only", commit, "--", *outs).splitlines() if outs else []
    for path in sorted(set(held) | set(changed.splitlines()) | set(written)):
        blob = subprocess.run(["git", "show", f"{commit}:{path}"], cwd=root, capture_output=True)
        if blob.returncode != 0:
            raise StageError(f"experiment {name}: cannot read {path} at {commit[:7]}")
        (into / path).parent.mkdir(parents=True, exist_ok=True)
        (into / path).write_bytes(blob.stdout)
    record = {"experiment": name, "experiment_commit": commit, "commit": baseline}
    (into / "run.json").write_text(json.dumps(record, indent=2) + "\n")
    return baseline
