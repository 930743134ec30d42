"""``scripts/compute_curve.py``: the compute study's curve from its recorded lengths (committed pipeline records as
input: the Large `plans` summary and its per-seed metrics, recorded as if run at two lengths)."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SCIENCE = REPO / "metrics" / "science"
KEY = "task.maze2d-large.pretrain.steps"
spec = importlib.util.spec_from_file_location("compute_curve", REPO / "scripts" / "compute_curve.py")
compute_curve = importlib.util.module_from_spec(spec)
spec.loader.exec_module(compute_curve)


def record(study: Path, steps: int, params_steps: int | None = None) -> Path:
    """A length's record as scripts/compute_study.sh keeps it, from the committed Large summary."""
    folder = study / f"steps-{steps}"
    folder.mkdir(parents=True)
    shutil.copy(SCIENCE / "maze2d-large.json", folder / "summary.json")
    shutil.copytree(SCIENCE / "maze2d-large" / "maze2d-large", folder / "maze2d-large")
    params = yaml.safe_load((REPO / "metrics" / "runs" / "science-large-seed2-plans" / "params.yaml").read_text())
    params["task"]["maze2d-large"]["pretrain"]["steps"] = params_steps or steps
    (folder / "params.yaml").write_text(yaml.safe_dump(params))
    return folder


def test_the_curve_holds_every_recorded_length_shortest_first(tmp_path: Path) -> None:
    study = tmp_path / "maze2d-large-compute"
    for steps in (40000, 5000):
        record(study, steps)
    (study / "steps-9000").mkdir()  # a length still running: no summary yet, left out
    out, figure = tmp_path / "curve.json", tmp_path / "curve.png"
    compute_curve.main([str(study), "--key", KEY, "--out", str(out), "--figure", str(figure)])
    data = json.loads(out.read_text())
    summary = json.loads((SCIENCE / "maze2d-large.json").read_text())["maze2d-large"]
    per_seed = json.loads((SCIENCE / "maze2d-large" / "maze2d-large" / "phase1-control.json").read_text())["seeds"]
    assert data["task"] == "maze2d-large" and data["key"] == KEY
    assert [entry["steps"] for entry in data["lengths"]] == [5000, 40000]
    entry = data["lengths"][0]
    assert entry["n_seeds"] == len(per_seed) == summary["phase_1"]["n_seeds"]
    assert entry["phase_0"]["score_ci_low"] == summary["phase_0"]["score_ci_low"]
    assert entry["gain"]["gain_mean"] == summary["phase_1"]["gain_mean"]
    assert entry["held_out_gain"]["gain_ci_high"] == summary["phase_1"]["held_out"]["gain_ci_high"]
    assert entry["control"]["score_mean"] == summary["phase_1"]["control"]["score_mean"]
    assert entry["per_seed"]["1"]["held_out_gain"] == per_seed["1"]["held_out"]["gain_mean"]
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_record_whose_params_disagree_with_its_length_is_refused(tmp_path: Path) -> None:
    study = tmp_path / "maze2d-large-compute"
    record(study, 5000, params_steps=4000)
    with pytest.raises(SystemExit, match=r"steps-5000: params.yaml has task.maze2d-large.pretrain.steps=4000"):
        compute_curve.curve(study, KEY)


def test_a_study_with_no_recorded_length_is_refused(tmp_path: Path) -> None:
    (tmp_path / "steps-100").mkdir()
    with pytest.raises(SystemExit, match="no recorded length"):
        compute_curve.curve(tmp_path, KEY)


# -- the committed study -----------------------------------------------------------------------------------------------

UMAZE_STUDY = SCIENCE / "maze2d-umaze-compute"
TABLE_MARKER = "<!-- compute: metrics/science/maze2d-umaze-compute.json -->"


def test_the_committed_curve_is_what_its_committed_records_give() -> None:
    """metrics/science/maze2d-umaze-compute.json is the script's output over the committed lengths, unedited."""
    committed = json.loads(UMAZE_STUDY.with_suffix(".json").read_text())
    assert compute_curve.curve(UMAZE_STUDY, "pretrain.steps") == committed
    assert len(committed["lengths"]) >= 3 and {e["n_seeds"] for e in committed["lengths"]} == {3}


def docs_table(text: str) -> str:
    lines = text.splitlines()
    start = lines.index(TABLE_MARKER) + 1
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
    return "\n".join(lines[start:end]) + "\n"


def test_the_docs_table_is_the_committed_curve() -> None:
    text = (REPO / "docs" / "results.md").read_text()
    data = json.loads(UMAZE_STUDY.with_suffix(".json").read_text())
    assert docs_table(text) == compute_curve.markdown_table(data)
    gain = data["lengths"][0]["gain"]
    gain["gain_mean"] += 0.1  # a changed figure no longer matches
    assert docs_table(text) != compute_curve.markdown_table(data)
