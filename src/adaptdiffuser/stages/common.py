"""Helpers shared by the stages (paths: :mod:`adaptdiffuser.layout`)."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # torch is imported where a device is resolved: the report stage starts without it
    import torch

#: a phase's gain over its control: mean ± standard error, 95 % intervals (over seeds; over episodes), win rate
GAIN_KEYS = (
    "gain_mean",
    "gain_stderr",
    "gain_ci_low",
    "gain_ci_high",
    "gain_episode_ci_low",
    "gain_episode_ci_high",
    "win_rate",
)


def save_over_seeds(per_seed: dict[int, dict], path: Path, task: str, stage: str, phase: int, root: Path) -> dict:
    """A stage's metrics of every training seed as one file (``root / path``; see
    :func:`adaptdiffuser.seed_metrics.over_seeds`), logged as an aggregate MLflow run when there are several seeds;
    returns the aggregate."""
    from adaptdiffuser.io import write_json
    from adaptdiffuser.seed_metrics import over_seeds
    from adaptdiffuser.tooling.run_records import log_over_seeds

    metrics = over_seeds(per_seed)
    write_json(root / path, metrics)
    log_over_seeds(task, stage, phase, metrics, root)
    return metrics


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when available; anything else is passed to torch (``cpu``, ``cuda``, ``cuda:1``)."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {name!r} requested but CUDA is not available")
    return device


def file_digest(path: Path) -> str:
    """SHA-256 of a file (names the exact data a model was trained on)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def source_digest(path: Path) -> str:
    """SHA-256 of a file, or of a folder's files (their relative paths and contents, in sorted order)."""
    if path.is_file():
        return file_digest(path)
    h = hashlib.sha256()
    for file in sorted(p for p in path.rglob("*") if p.is_file()):
        h.update(str(file.relative_to(path)).encode() + b"\0" + file_digest(file).encode())
    return h.hexdigest()


def phase_entries(task_summary: dict) -> list[tuple[int, dict]]:
    """``(k, entry)`` of every ``phase_k`` entry of one task's summary, in phase order."""
    phases = [(int(k.removeprefix("phase_")), entry) for k, entry in task_summary.items() if k.startswith("phase_")]
    return sorted(phases, key=lambda item: item[0])


def unseen_scores(metrics: dict) -> list[str]:
    """The scores an unseen task's metrics report (``score`` and, e.g., KUKA's ``setup1_score``): the names whose
    ``<name>_mean`` they hold."""
    return [key.removesuffix("_mean") for key in metrics if key.endswith("score_mean")]
