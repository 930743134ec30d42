"""Export: one of our trajectory files (a task's dataset, or an evolution phase's selected data) as a Minari
dataset, with the task's env spec, so that others can train on it with ``minari.load_dataset``."""

from __future__ import annotations

import json
import re
from pathlib import Path

from adaptdiffuser.config import Params
from adaptdiffuser.data.schema import read_trajectories
from adaptdiffuser.family_registry import get_family


def run_export_minari(
    params: Params, task_name: str, data: Path, dataset_id: str, root: Path | None = None, force: bool = False
) -> Path:
    """Write the trajectory file ``data`` of task ``task_name`` as the Minari dataset ``dataset_id`` in the store
    ``root`` (default: the local Minari store); refuse an existing id unless ``force``. Returns its folder."""
    from adaptdiffuser.data.minari_io import export_minari

    task = params.resolve(task_name)
    traj = read_trajectories(data, env=task.name)
    env_spec, obs_space, act_space = get_family(task.family).export_spec(task)
    meta = traj.metadata
    phase = meta.get("generator", {}).get("phase")
    if phase is None:  # selected data lives under data/<task>/phase<k>/; the expert data is phase 0's
        found = re.search(r"phase(\d+)", str(data))
        phase = int(found.group(1)) if found else 0
    about = {
        "task": task.name,
        "file": str(data),
        "source": meta["source"],
        "phase": phase,
        "generator": meta.get("generator", {}),
    }
    description = (
        f"adaptdiffuser {meta['source']} data of task {task.name} from {data}: observations and actions as the "
        f"project's Parquet schema holds them (each episode's n observations and the n - 1 transitions between "
        f"them). Details: {json.dumps(about, default=str, sort_keys=True)}"
    )
    return export_minari(traj, dataset_id, env_spec, obs_space, act_space, description, root=root, force=force)
