"""The dependency tracer and the check of dvc.yaml's deps against traces.

The check on the real pipeline runs in tests/test_pipeline.py (its smoke ``dvc repro`` runs with the tracer on);
these tests make sure the tracer sees what a stage uses, so that check cannot pass on an empty trace.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from deps_trace import (
    ENV_VAR,
    PARQUET_READERS,
    StageDeps,
    StageTrace,
    check,
    check_stage,
    is_inert,
    missing_message,
    traced_env,
    unused_by_group,
)
from dvc.repo import Repo

REPO = Path(__file__).resolve().parents[1]

PROBE = """\
import os
from pathlib import Path

from adaptdiffuser.cli import run_stage

try:
    run_stage("check")  # reads params.yaml (the tracer started with the interpreter: tests/trace_hook)
except SystemExit as done:
    assert done.code in (0, None), done.code

import pyarrow.parquet as pq
import torch

import adaptdiffuser.derived_seeds  # a project module, imported after the tracer started

Path("data/input.txt").read_text()
pq.read_table("data/table.parquet")  # opened in C++: seen through the wrapped reader
torch.load("models/model.pt", weights_only=True)
Path("data/own.txt").write_text("written here first")
Path("data/own.txt").read_text()  # read back after writing it: no input
Path(os.environ["OUTSIDE"]).read_text()  # outside the project
try:
    open("data/missing.txt")
except FileNotFoundError:
    pass
sorted(Path("models").iterdir())
"""


def test_tracer_records_modules_reads_and_listings_of_a_stage(tmp_path: Path) -> None:
    project, traces = tmp_path / "project", tmp_path / "traces"
    (project / "pipeline").mkdir(parents=True)
    (project / "data").mkdir()
    (project / "models").mkdir()
    shutil.copy2(REPO / "params.yaml", project / "params.yaml")
    (project / "pipeline/probe.py").write_text(PROBE)
    (project / "data/input.txt").write_text("input")
    pq.write_table(pa.table({"x": [1, 2]}), project / "data/table.parquet")
    torch.save({"w": torch.zeros(2)}, project / "models/model.pt")
    outside = tmp_path / "outside.txt"
    outside.write_text("not a project file")
    env = dict(os.environ, OUTSIDE=str(outside), DVC_STAGE="probe@x", DVC_ROOT=str(project), **traced_env(traces))
    out = subprocess.run([sys.executable, "pipeline/probe.py"], cwd=project, env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr

    (file,) = traces.glob("probe@x-*.json")
    trace = json.loads(file.read_text())
    assert trace["stage"] == "probe@x" and trace["root"] == str(project.resolve())
    reads = set(trace["reads"]) - {"pipeline/probe.py"}  # libraries may read the script's source (linecache)
    assert reads == {"data/input.txt", "data/table.parquet", "models/model.pt", "params.yaml"}
    # pipeline/ is the script's folder, first on sys.path: the import system lists it for every import
    assert set(trace["listed"]) - {"pipeline"} == {"models"}
    modules = set(trace["modules"])
    assert {"pipeline/probe.py", "src/adaptdiffuser/cli.py", "src/adaptdiffuser/derived_seeds.py"} <= modules
    assert "src/adaptdiffuser/config/loader.py" in modules
    assert all(m.startswith(("src/adaptdiffuser/", "pipeline/")) and m.endswith(".py") for m in modules)


def test_stages_do_not_start_the_tracer_without_the_variable(tmp_path: Path) -> None:
    (tmp_path / "pipeline").mkdir()
    shutil.copy2(REPO / "params.yaml", tmp_path / "params.yaml")
    script = (
        "import sys\nfrom adaptdiffuser.cli import run_stage\n"
        "try:\n    run_stage('check')\n"
        "except SystemExit:\n    print('tracer', 'deps_trace' in sys.modules)\n"
    )
    (tmp_path / "pipeline/check.py").write_text(script)
    hook = {key: value for key, value in traced_env(tmp_path / "traces").items() if key != ENV_VAR}
    env = {key: value for key, value in os.environ.items() if key != ENV_VAR} | hook | {"DVC_STAGE": "check@x"}
    out = subprocess.run([sys.executable, "pipeline/check.py"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip().endswith("tracer False"), out.stdout + out.stderr


DVC_YAML = """\
stages:
  train:
    foreach: [a, b]
    do:
      cmd: python pipeline/train.py ${item}
      deps:
        - pipeline/train.py
        - src/adaptdiffuser/config
        - data/${item}.txt
        - data/never.txt
      params: [seed]
      outs:
        - models/${item}
"""


def _trace(folder: Path, stage: str, modules: list[str], reads: list[str], listed: list[str]) -> None:
    folder.mkdir(exist_ok=True)
    data = {"stage": stage, "argv": [], "root": "", "modules": modules, "reads": reads, "listed": listed}
    (folder / f"{stage}-1.json").write_text(json.dumps(data))


def test_check_names_each_stage_and_the_paths_its_deps_miss(tmp_path: Path) -> None:
    (tmp_path / "dvc.yaml").write_text(DVC_YAML)
    (tmp_path / "params.yaml").write_text("seed: 0\n")
    (tmp_path / "src/adaptdiffuser").mkdir(parents=True)
    (tmp_path / "src/adaptdiffuser/__init__.py").write_text('"""Docstring only."""\n\n__version__ = "1"\n')
    with Repo.init(str(tmp_path), no_scm=True):
        pass
    traces = tmp_path / "traces"
    common = ["pipeline/train.py", "src/adaptdiffuser/__init__.py", "src/adaptdiffuser/config/loader.py"]
    _trace(traces, "train@a", [*common, "src/adaptdiffuser/io.py"], ["data/a.txt", "params.yaml"], ["data"])
    with pytest.raises(KeyError, match="train@b"):
        check(tmp_path, traces)
    # b also reads a's data and its own model (an out), and lists a folder no dep reaches
    _trace(traces, "train@b", common, ["data/b.txt", "data/a.txt", "models/b/w.pt"], ["results"])

    reports = check(tmp_path, traces)
    assert reports["train@a"].missing == ["src/adaptdiffuser/io.py"]
    assert reports["train@b"].missing == ["data/a.txt", "results"]
    assert reports["train@a"].unused == ["data/never.txt"]
    message = missing_message(reports)
    assert "train@a: add to its deps in dvc.yaml: src/adaptdiffuser/io.py" in message
    assert "train@b: add to its deps in dvc.yaml: data/a.txt, results" in message
    assert unused_by_group(reports) == {"train": ["data/never.txt"]}


def test_indirect_reads_need_an_upstream_stage_that_writes_them(tmp_path: Path) -> None:
    stage = StageDeps(deps=["models/p1"], params_files=[], outs=["models/p2"], upstream_outs=["data/p1/selected"])
    trace = StageTrace(reads={"data/p1/selected/s0.parquet", "data/p2/selected/s0.parquet"})
    report = check_stage(stage, trace, tmp_path, indirect=["data/*/selected/*"])
    assert report.missing == ["data/p2/selected/s0.parquet"]  # not upstream: phase 2's own data must be a dep
    assert check_stage(stage, trace, tmp_path).missing == sorted(trace.reads)


def test_only_docstring_and_dunder_modules_are_inert(tmp_path: Path) -> None:
    inert, live = tmp_path / "inert.py", tmp_path / "live.py"
    inert.write_text('"""Package."""\n\nfrom __future__ import annotations\n\n__all__ = ["x"]\n')
    live.write_text('"""Package."""\n\nfrom adaptdiffuser.io import write_json\n')
    assert is_inert(inert) and not is_inert(live) and not is_inert(tmp_path / "absent.py")


def test_project_reads_files_only_in_ways_the_tracer_sees() -> None:
    """Parquet is read through the pyarrow.parquet readers the tracer wraps (called on the module, so the wrappers
    apply); nothing else opens project files in C++ (memory maps, other pyarrow readers, mmap'd checkpoints)."""
    writers = {"write_table", "ParquetWriter", "write_to_dataset", "write_metadata"}
    for path in sorted((REPO / "src").rglob("*.py")) + sorted((REPO / "pipeline").glob("*.py")):
        text = path.read_text()
        for line in re.findall(r"^\s*(?:import|from) pyarrow\S*.*$", text, flags=re.M):
            assert line.strip() in ("import pyarrow as pa", "import pyarrow.parquet as pq"), f"{path}: {line}"
        assert set(re.findall(r"\bpq\.(\w+)", text)) <= set(PARQUET_READERS) | writers, path
        assert not re.search(r"\bpa\.(memory_map|OSFile|input_stream|ipc|feather|csv|dataset)\b", text), path
        assert not re.search(r"mmap\s*=\s*True", text), path
