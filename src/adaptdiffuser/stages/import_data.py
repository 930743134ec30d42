"""Stage ``import-data``: a task's dataset from outside (a D4RL HDF5 file or a Minari dataset, ``imports.<task>``)
instead of the collect stage, converted by the task's family and written as our Parquet schema."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from adaptdiffuser.config import ConfigError, Params
from adaptdiffuser.data.d4rl import ExternalData, read_d4rl
from adaptdiffuser.data.schema import write_trajectories
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.io import write_json
from adaptdiffuser.layout import collect_dir, dataset_path
from adaptdiffuser.stages.common import file_digest, source_digest
from adaptdiffuser.tooling.run_records import stage_run

#: what the import writes into the task's collect folder (in place of the collect stage's ``collect.json``)
IMPORT_SUMMARY = "import.json"


def read_external(fmt: str, path: str) -> ExternalData:
    """The external data ``path`` names, read by its ``fmt`` (``d4rl`` or ``minari``)."""
    if fmt == "d4rl":
        return read_d4rl(path)
    from adaptdiffuser.data.minari_io import read_minari

    return read_minari(path)


def run_import(params: Params, task_name: str, root: Path, progress: bool = True) -> Path:
    """Stage ``import-data@<task>``: write ``data/<task>/dataset.parquet`` from ``imports.<task>`` and
    ``models/<task>/collect/import.json`` (source, its SHA-256, counts)."""
    task = params.resolve(task_name)
    spec = params.imports.get(task.name)
    if spec is None:
        raise ConfigError(f"imports: has no entry for task {task.name}; add imports.{task.name}: {{format, path}}")
    family = get_family(task.family)
    logged = {"task": task.section("settings"), "import": dataclasses.asdict(spec), "family": family.describe(task)}
    with stage_run(task.name, "import", 0, logged, root) as run:
        raw = read_external(spec.format, spec.path)
        traj = family.from_external(task, raw)
        source_sha = source_digest(Path(raw.source))
        traj.metadata["generator"]["source_sha256"] = source_sha
        out = root / dataset_path(task.name)
        write_trajectories(out, traj)
        stats = {"steps": len(traj), "episodes": len(traj.episodes()), "reward_mean": float(traj.reward.mean())}
        run.log_metrics(stats)
        digest = file_digest(out)
        run.log_params({"data.sha256": digest, "data.source_sha256": source_sha})
        summary = {
            "imported": True,
            "format": spec.format,
            "source": raw.source,
            "source_sha256": source_sha,
            "dataset": str(dataset_path(task.name)),
            "sha256": digest,
            **stats,
            **family.describe(task),
        }
        write_json(root / collect_dir(task.name) / IMPORT_SUMMARY, summary)
    return out
