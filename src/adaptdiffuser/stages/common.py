"""Path conventions and helpers shared by the stages."""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch

EXPERT_DATA = Path("data/expert.parquet")
REFERENCE = Path("metrics/reference.json")
SUMMARY = Path("metrics/summary.json")


def model_dir(phase: int) -> Path:
    return Path(f"models/phase{phase}")


def results_dir(phase: int) -> Path:
    return Path(f"results/phase{phase}")


def plots_dir(phase: int) -> Path:
    return Path(f"plots/phase{phase}")


PHASE_METRICS = Path("metrics/phases")
SCORE_TABLE = Path("metrics/score_by_phase.csv")
REPORT_PLOT = Path("plots/report/score_by_phase.png")


def phase_metrics_path(phase: int) -> Path:
    """Evaluation metrics of a phase (written by its evaluate stage)."""
    return PHASE_METRICS / f"phase{phase}.json"


def discriminator_metrics_path(phase: int) -> Path:
    """The discriminator report of an evolution phase (written by its discriminate stage)."""
    return PHASE_METRICS / f"phase{phase}-discriminator.json"


def coin_metrics_path(phase: int) -> Path:
    """Gold-coin metrics of a phase (written by its evaluate-coin stage)."""
    return PHASE_METRICS / f"phase{phase}-coin.json"


def coin_plots_dir(phase: int) -> Path:
    return Path(f"plots/coin/phase{phase}")


def generated_path(phase: int) -> Path:
    return Path(f"data/phase{phase}/generated.parquet")


def selected_path(phase: int) -> Path:
    return Path(f"data/phase{phase}/selected.parquet")


def discriminator_plot_path(phase: int) -> Path:
    return Path(f"plots/discriminator/phase{phase}.png")


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when available; anything else is passed to torch (``cpu``, ``cuda``, ``cuda:1``)."""
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
