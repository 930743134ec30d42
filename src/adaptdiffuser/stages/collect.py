"""Stage ``collect``: a task's offline dataset (its family's recipe), as Parquet."""

from __future__ import annotations

from pathlib import Path

from adaptdiffuser.config import Params
from adaptdiffuser.contract import TaskFiles
from adaptdiffuser.data.schema import write_trajectories
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.io import write_json
from adaptdiffuser.layout import collect_dir, dataset_path
from adaptdiffuser.stages.common import file_digest
from adaptdiffuser.stages.training_data import code_digest
from adaptdiffuser.tooling.run_records import stage_run


def run_collect(params: Params, task_name: str, root: Path, progress: bool = True) -> Path:
    """Stage ``collect@<task>``: write ``data/<task>/dataset.parquet`` and ``models/<task>/collect/collect.json``
    (beside the family's own outputs there)."""
    task = params.resolve(task_name)
    family = get_family(task.family)
    logged = {"task": task.section("settings"), "family": family.describe(task)}
    with stage_run(task.name, "collect", 0, logged, root) as run:
        traj = family.collect(task, TaskFiles(root, task.name, code=code_digest(root, task.name)), progress)
        out = root / dataset_path(task.name)
        write_trajectories(out, traj)
        stats = {"steps": len(traj), "episodes": len(traj.episodes()), "reward_mean": float(traj.reward.mean())}
        run.log_metrics(stats)
        digest = file_digest(out)
        run.log_params({"data.sha256": digest})
        summary = {"dataset": str(dataset_path(task.name)), "sha256": digest, **stats, **family.describe(task)}
        write_json(root / collect_dir(task.name) / "collect.json", summary)
    return out
