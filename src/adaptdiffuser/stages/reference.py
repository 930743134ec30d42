"""Stage ``reference``: what 0 and 100 of a task's normalized score mean (its family decides how)."""

from __future__ import annotations

from pathlib import Path

from adaptdiffuser.config import Params
from adaptdiffuser.contract import TaskFiles
from adaptdiffuser.errors import StageError
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.io import write_json
from adaptdiffuser.layout import reference_path
from adaptdiffuser.tooling.run_records import flatten, stage_run


def run_reference(params: Params, task_name: str, root: Path, progress: bool = True) -> dict:
    """Stage ``reference@<task>``: write ``metrics/<task>/reference.json`` with ``r_min`` and ``r_max``."""
    task = params.resolve(task_name)
    family = get_family(task.family)
    logged = {"task": task.section("settings"), "evaluate": task.section("evaluate")}
    with stage_run(task.name, "reference", 0, logged, root) as run:
        ref = family.reference(task, TaskFiles(root, task.name), progress)
        if not ref["r_max"] > ref["r_min"]:
            raise StageError(f"reference of {task.name}: R_max {ref['r_max']} does not exceed R_min {ref['r_min']}")
        write_json(root / reference_path(task.name), ref)
        run.log_metrics({k: v for k, v in flatten(ref).items() if isinstance(v, float)})
    return ref
