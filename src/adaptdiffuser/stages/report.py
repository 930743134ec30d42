"""Stage ``report``: score by phase as a PNG with error bars and a CSV table for ``dvc plots show``."""

from __future__ import annotations

import csv
from pathlib import Path

from adaptdiffuser.io import atomic_path, read_json
from adaptdiffuser.plots import save_score_by_phase
from adaptdiffuser.stages.common import REPORT_PLOT, SCORE_TABLE, SUMMARY

TABLE_COLUMNS = ("phase", "score_mean", "score_stderr", "success_rate", "return_mean", "n_episodes", "kept")


def score_table(summary: dict) -> list[dict]:
    """One row per phase, in phase order, from ``metrics/summary.json``."""
    rows = []
    for key, entry in summary.items():
        nav = entry["navigation"]
        rows.append(
            {
                "phase": int(key.removeprefix("phase_")),
                **{k: nav[k] for k in ("score_mean", "score_stderr", "success_rate", "return_mean", "n_episodes")},
                "kept": entry.get("discriminator", {}).get("kept", 0),
            }
        )
    return sorted(rows, key=lambda row: row["phase"])


def run_report(root: Path) -> list[dict]:
    """Write ``metrics/score_by_phase.csv`` and ``plots/report/score_by_phase.png`` from the summary."""
    rows = score_table(read_json(root / SUMMARY, "metrics/summary.json (run the summarize stage)"))
    with atomic_path(root / SCORE_TABLE) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=TABLE_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    save_score_by_phase(
        [r["phase"] for r in rows],
        [r["score_mean"] for r in rows],
        [r["score_stderr"] for r in rows],
        root / REPORT_PLOT,
    )
    return rows
