"""Stage ``summarize``: the per-phase metrics merged into ``metrics/summary.json``."""

from __future__ import annotations

from pathlib import Path

from adaptdiffuser.io import read_json, write_json
from adaptdiffuser.stages.common import SUMMARY, phase_metrics_path


def run_summarize(root: Path, phases: list[int]) -> dict:
    """Stage ``summarize``: merge the per-phase metrics into ``metrics/summary.json``."""
    summary = {
        f"phase_{k}": read_json(root / phase_metrics_path(k), f"metrics of phase {k} (run its evaluate stage)")
        for k in phases
    }
    write_json(root / SUMMARY, summary)
    return summary
