"""Training seeds run apart, pooled: runs of one profile that differ only in ``seeds`` (folders holding a run's
``params.yaml`` and ``metrics/``, or DVC experiments, one per seed, as ``adaptdiffuser seeds queue`` queues them),
merged into the metrics and summaries one run over all their seeds writes.

A science profile's seeds may take longer than a machine lasts, or run faster side by side on more hardware: run
one seed per run (``dvc queue start -j N`` runs N queued seeds at once) and pool them. A training seed's training,
generation and evaluation depend on that seed alone (``derived_seeds.training_seed``), and every metrics file
holds each seed's metrics beside their aggregate (``seed_metrics.over_seeds``), so the pooled files are the ones
the multi-seed run writes. Each set of task metrics a run holds is pooled: ``metrics/tasks/`` (its last pass) and every
per-pass copy under ``metrics/science/<name>/`` (``scripts/science_maze.sh``: one a recipe), each with its summary.

Where each run's phase 0 came from (``pretrained``: imported from a folder; ``pretrain_tasks``: trained in the run)
is provenance, not a setting: runs that pool may differ there, as long as every other setting, the pretraining
recipe (``pretrain``) included, is the same. The pooled ``run.json`` names each run's source.
"""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from adaptdiffuser.config import params_from_dict
from adaptdiffuser.errors import StageError
from adaptdiffuser.io import atomic_dir, write_json
from adaptdiffuser.layout import SUMMARY
from adaptdiffuser.seed_metrics import over_seeds
from adaptdiffuser.stages.summarize import build_summary
from adaptdiffuser.tooling.dvc_experiments import export_experiment

TASKS_SET = "tasks"  # metrics/tasks/: the run's own (its last pass)
#: params that say where a run's phase 0 came from (imported or trained here), not how it was trained
PHASE0_SOURCE = ("pretrained", "pretrain_tasks")


@dataclass(frozen=True)
class SavedRun:
    """One run: its folder, params (as written), training seeds, the digest of each task's code (from its
    ``dvc.lock``, where it has one) and how errors name it (its folder, or its experiment)."""

    folder: Path
    raw: dict[str, Any]
    seeds: tuple[int, ...]
    code: dict[str, str]
    label: str


def load_run(folder: Path) -> SavedRun:
    """A run's folder (``params.yaml``, ``metrics/``, optionally ``dvc.lock`` and ``run.json``); a clear error for a
    folder that is not one."""
    params_path, lock_path = folder / "params.yaml", folder / "dvc.lock"
    for path in (params_path, folder / "metrics"):
        if not path.exists():
            raise StageError(f"{folder} is not a run's folder: it has no {path.name}")
    raw = yaml.safe_load(params_path.read_text())
    seeds = tuple(params_from_dict(raw).seeds)
    code: dict[str, str] = {}
    lock = yaml.safe_load(lock_path.read_text()) if lock_path.exists() else None
    for stage in (lock or {}).get("stages", {}).values():
        for dep in stage.get("deps", []):
            if dep["path"].startswith("code/"):
                code[dep["path"]] = dep["md5"]
    experiment = _run_record(folder).get("experiment")
    return SavedRun(folder, raw, seeds, code, f"experiment {experiment}" if experiment else str(folder))


def _first_difference(a: Any, b: Any, key: str = "") -> str | None:
    """The dotted key of the first setting where ``a`` and ``b`` differ (``""`` for the whole), or None."""
    if isinstance(a, dict) and isinstance(b, dict):
        for name in sorted(set(a) | set(b), key=str):
            inner = _first_difference(a.get(name), b.get(name), f"{key}.{name}" if key else str(name))
            if inner is not None:
                return inner
        return None
    return None if a == b else key


def _settings(raw: dict[str, Any]) -> dict[str, Any]:
    """A run's params less what pooled runs may differ in: its seeds and its phase 0's source."""
    return {**{key: value for key, value in raw.items() if key not in PHASE0_SOURCE}, "seeds": None}


def phase0_source(raw: dict[str, Any]) -> dict[str, Any]:
    """Where a run's phase 0 came from: its ``pretrained`` folders and its ``pretrain_tasks``, as its params say."""
    return {key: raw.get(key) for key in PHASE0_SOURCE}


def check_poolable(runs: list[SavedRun]) -> None:
    """Runs pool only when their params differ in ``seeds`` and the source of phase 0 alone, no seed is in two of
    them and their tasks ran the same code (where their ``dvc.lock`` says); a one-line error naming the first that
    does not hold."""
    if len(runs) < 2:
        raise StageError("pooling needs two runs or more")
    first = runs[0]
    owner = {seed: first.label for seed in first.seeds}
    for run in runs[1:]:
        key = _first_difference(_settings(first.raw), _settings(run.raw))
        if key is not None:
            raise StageError(f"{run.label} and {first.label} differ in {key!r}, not only in seeds: they do not pool")
        for path in sorted(set(first.code) & set(run.code)):
            if first.code[path] != run.code[path]:
                raise StageError(f"{run.label} and {first.label} ran other code ({path} differs): they do not pool")
        for seed in run.seeds:
            if seed in owner:
                raise StageError(f"training seed {seed} is in both {owner[seed]} and {run.label}")
            owner[seed] = run.label


def metric_sets(folder: Path) -> dict[str, Path]:
    """A saved run's sets of task metrics, by name: ``tasks`` (``metrics/tasks/``) and ``science/<name>`` for each
    per-pass copy (a folder under ``metrics/science/`` whose task folders hold a ``phase0.json``)."""
    sets = {TASKS_SET: folder / "metrics" / "tasks"} if (folder / "metrics" / "tasks").is_dir() else {}
    science = folder / "metrics" / "science"
    if science.is_dir():
        for path in sorted(science.iterdir()):
            if path.is_dir() and any(path.glob("*/phase0.json")):
                sets[f"science/{path.name}"] = path
    return sets


def pool_file(files: list[Path]) -> dict[str, Any]:
    """One metrics file of several runs as one run over all their seeds writes it; a file without seeds (the
    reference) must be the same in every run."""
    contents = [json.loads(path.read_text()) for path in files]
    if not all("seeds" in content for content in contents):
        if any(content != contents[0] for content in contents[1:]):
            raise StageError(f"{files[0].name} differs between the runs ({files[0]}, ...): they do not pool")
        return contents[0]
    per_seed: dict[int, Any] = {}
    for path, content in zip(files, contents, strict=True):
        for seed, metrics in content["seeds"].items():
            if int(seed) in per_seed:
                raise StageError(f"{path} holds seed {seed}, which another run's file holds too: they do not pool")
            per_seed[int(seed)] = metrics
    return over_seeds({seed: per_seed[seed] for seed in sorted(per_seed)})


def pool_set(folders: list[Path], into: Path, tasks: set[str], committed: dict[str, bytes] | None = None) -> list[str]:
    """Every metrics file of the runs' ``tasks`` that all ``folders`` hold (``<task>/<name>.json``), pooled into
    ``into``, and each file of ``committed`` (relative path -> content) of those tasks that none of them holds and
    that no seed wrote (a reference), as it is there; returns the files some runs lack (left out). Another task's
    files (a pass's copy of ``metrics/tasks/`` holds the commit's files of the tasks the run did not run) are not
    the runs' own: they are not pooled."""
    held = [
        {rel for path in folder.glob("*/*.json") if (rel := path.relative_to(folder).as_posix()).split("/")[0] in tasks}
        for folder in folders
    ]
    common, anywhere = set.intersection(*held), set.union(*held)
    for rel in sorted(common):
        write_json(into / rel, pool_file([folder / rel for folder in folders]))
    tasks = {rel.split("/")[0] for rel in anywhere}
    for rel, content in sorted((committed or {}).items()):
        if rel not in anywhere and rel.split("/")[0] in tasks and "seeds" not in json.loads(content):
            (into / rel).parent.mkdir(parents=True, exist_ok=True)  # a file of no seed's: the same for every run
            (into / rel).write_bytes(content)
    return sorted(anywhere - common)


def committed_task_metrics(repo: Path, commit: str | None) -> dict[str, bytes]:
    """The files under ``metrics/tasks/`` of ``commit`` in the git repository ``repo`` (relative to it), which a
    run's folder leaves out when the run wrote them as its commit holds them (a reference); none when the commit is
    not there."""
    if not commit:
        return {}
    git = ["git", "-C", str(repo)]
    listed = subprocess.run([*git, "ls-tree", "-r", "--name-only", commit, "metrics/tasks/"], capture_output=True)
    if listed.returncode != 0:
        return {}
    files = {}
    for name in listed.stdout.decode().split():
        if name.endswith(".json"):
            shown = subprocess.run([*git, "show", f"{commit}:{name}"], capture_output=True, check=True)
            files[name.removeprefix("metrics/tasks/")] = shown.stdout
    return files


def summary_of(params_raw: dict[str, Any], tasks_dir: Path) -> dict[str, Any]:
    """The summary the ``summarize`` stage writes for a folder of task metrics laid out as ``metrics/tasks/``."""
    with tempfile.TemporaryDirectory() as scratch:
        (Path(scratch) / "metrics").mkdir()
        os.symlink(tasks_dir.resolve(), Path(scratch) / "metrics" / "tasks")
        return build_summary(params_from_dict(params_raw), Path(scratch))


def pool_runs(
    folders: list[Path], into: Path, repo: Path | None = None, experiments: list[str] | tuple[str, ...] = ()
) -> list[str]:
    """Pool the runs in ``folders`` and the DVC ``experiments`` of ``repo`` (default: the working directory) into
    ``into`` (replaced whole, or left as it was on an error): ``params.yaml`` with every seed (and the first run's
    phase-0 source), each set of task metrics all runs hold with its summary (``metrics/summary.json`` for
    ``metrics/tasks/``, ``metrics/science/<name>.json`` for a pass), and ``run.json`` naming the runs and the source
    of each one's phase 0. Returns one line per set pooled and per file left out."""
    repo = repo or Path.cwd()
    with tempfile.TemporaryDirectory() as scratch:
        exported = []
        for i, name in enumerate(experiments):
            folder = Path(scratch) / f"experiment{i}"
            folder.mkdir()
            export_experiment(repo, name, folder)
            exported.append(folder)
        return _pool([*folders, *exported], into, repo)


def _pool(folders: list[Path], into: Path, repo: Path) -> list[str]:
    runs = [load_run(folder) for folder in folders]
    check_poolable(runs)
    seeds = sorted(seed for run in runs for seed in run.seeds)
    raw = {**runs[0].raw, "seeds": seeds}
    tasks = set(params_from_dict(raw).tasks)
    sets = [metric_sets(run.folder) for run in runs]
    names = [name for name in sets[0] if all(name in s for s in sets)]
    if not names:
        raise StageError("the runs hold no set of task metrics in common (metrics/tasks/, metrics/science/<name>/)")
    records = [_run_record(run.folder) | {"phase0_source": phase0_source(run.raw)} for run in runs]
    commits = [record.get("commit") for record in records]
    cpus = sorted({record["cpu"] for record in records if "cpu" in record})
    lines = (
        [f"the seeds ran on {len(cpus)} CPUs: {'; '.join(cpus)} (say so beside the results)"] if len(cpus) > 1 else []
    )
    if any(record["phase0_source"] != records[0]["phase0_source"] for record in records):
        lines.append("the runs' phases 0 came from different sources (imported or trained): run.json names each run's")
    with atomic_dir(into) as build:
        (build / "params.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))
        write_json(build / "run.json", {"pooled": records, "seeds": seeds})
        for name in names:
            target = build / "metrics" / name
            committed = committed_task_metrics(repo, commits[0]) if name == TASKS_SET else {}
            left_out = pool_set([s[name] for s in sets], target, tasks, committed if len(set(commits)) == 1 else {})
            lines += [f"{name}: {rel} left out (not in every run)" for rel in left_out]
            summary_path = SUMMARY if name == TASKS_SET else Path("metrics") / f"{name}.json"
            try:
                write_json(build / summary_path, summary_of(raw, target))
                lines.append(f"{name}: seeds {seeds} pooled, summary {into / summary_path}")
            except FileNotFoundError as missing:  # a phase not every run finished: its files pooled, no summary
                lines.append(f"{name}: seeds {seeds} pooled, no summary ({missing})")
    return lines


def _run_record(folder: Path) -> dict[str, Any]:
    record = json.loads((folder / "run.json").read_text()) if (folder / "run.json").exists() else {}
    if "experiment" in record:  # exported into a scratch folder: named by the experiment and its commit alone
        return {key: record[key] for key in ("experiment", "experiment_commit", "commit")}
    kept = ("commit", "profile", "settings", "phase0", "cpu")
    return {"folder": str(folder), **{key: record[key] for key in kept if key in record}}
