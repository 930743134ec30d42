"""Stage ``summarize``: the per-phase metrics merged into ``metrics/summary.json``."""

from __future__ import annotations

from pathlib import Path

from adaptdiffuser.io import read_json, write_json
from adaptdiffuser.stages.common import SUMMARY, coin_metrics_path, discriminator_metrics_path, phase_metrics_path

SUMMARY_DISCRIMINATOR_KEYS = ("generated", "kept", "kept_fraction", "tracking_error_mean")


def run_summarize(root: Path, phases: list[int]) -> dict:
    """Merge each phase's evaluation metrics, its gold-coin metrics and, for phases >= 1, its discriminator
    counts into ``metrics/summary.json`` as ``{"phase_k": {"navigation", "gold_coin", "discriminator"}}``."""
    summary = {}
    for k in phases:
        entry = read_json(root / phase_metrics_path(k), f"metrics of phase {k} (run its evaluate stage)")
        entry.update(read_json(root / coin_metrics_path(k), f"gold-coin metrics of phase {k} (run evaluate-coin)"))
        if k > 0:
            report = read_json(root / discriminator_metrics_path(k), f"discriminator report of phase {k}")
            entry["discriminator"] = {key: report[key] for key in SUMMARY_DISCRIMINATOR_KEYS}
        summary[f"phase_{k}"] = entry
    write_json(root / SUMMARY, summary)
    return summary
