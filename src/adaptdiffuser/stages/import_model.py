"""Stage ``import-model``: a task's phase-0 models from a folder of already trained ones (``pretrained.<task>``)
instead of the pretrain stage: from this repository's history or another machine's run.

The folder holds one model folder per training seed, ``seed<s>/``, as the pretrain stage writes them
(``models/<task>/phase0/``): ``model.pt``, ``ema.pt``, ``normalizer.json``, ``config.json`` and optionally
``optimizer.pt``, ``train_loss.png`` and ``value/``. Every seed of ``seeds`` is checked before anything is
written: the architecture its config names must be the task's (``model``, ``diffusion``, observation and action
sizes, family and conditioning), its weights must load into it, and its normalizer must be the one the task's data
gives. Each seed's folder is then copied byte for byte to ``models/<task>/phase0/seed<s>/``.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from adaptdiffuser.checkpoint import BUNDLE_FILES, load_bundle
from adaptdiffuser.config import ConfigError, Params, TaskParams
from adaptdiffuser.data.normalizer import fit_normalizer
from adaptdiffuser.data.windows import joint_array
from adaptdiffuser.errors import StageError
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.io import atomic_dir, read_json, write_json
from adaptdiffuser.layout import model_dir, phase_models_dir, seed_name
from adaptdiffuser.stages.common import source_digest
from adaptdiffuser.stages.training_data import expert_training_data
from adaptdiffuser.stages.value_function import run_value
from adaptdiffuser.tooling.run_records import stage_run

#: what the import writes beside the seed folders: the source folder, each seed's digest and data check
IMPORT_SUMMARY = "import.json"
#: how far a saved normalizer may be from the one refitted on the task's data (JSON keeps float64 exactly)
NORMALIZER_RTOL = 1e-6


def pretrained_folder(params: Params, task: str, root: Path) -> Path:
    """The folder ``pretrained.<task>`` names (relative paths from the project root)."""
    folder = params.pretrained.get(task)
    if folder is None:
        raise ConfigError(f"pretrained: has no entry for task {task}; add pretrained.{task}: <folder of seed<s>/>")
    path = Path(folder)
    return path if path.is_absolute() else root / path


def _differences(saved: Any, expected: Any, prefix: str) -> list[str]:
    """``key: saved vs expected`` for every leaf of two JSON-like values that differs (lists compared whole)."""
    if isinstance(saved, dict) and isinstance(expected, dict):
        out: list[str] = []
        for key in sorted(set(saved) | set(expected)):
            if key not in saved:
                out.append(f"{prefix}{key} absent, task has {json.dumps(expected[key])}")
            elif key not in expected:
                out.append(f"{prefix}{key} is {json.dumps(saved[key])}, task has no such key")
            else:
                out += _differences(saved[key], expected[key], f"{prefix}{key}.")
        return out
    if json.loads(json.dumps(saved)) != json.loads(json.dumps(expected)):
        return [f"{prefix.rstrip('.')} is {json.dumps(saved)}, task has {json.dumps(expected)}"]
    return []


def check_shape(config: dict[str, Any], task: TaskParams, obs_dim: int, act_dim: int) -> list[str]:
    """What in a saved model's ``config.json`` differs from the model ``task`` builds (empty: the same)."""
    family = get_family(task.family)
    expected = {
        "family": task.family,
        "conditioning": family.conditioning,
        "obs_dim": obs_dim,
        "act_dim": act_dim,
        "model": asdict(task.model),
        "diffusion": asdict(task.diffusion),
    }
    saved = {key: config.get(key, "absent") for key in expected}
    return _differences(saved, expected, "")


def check_normalizer(saved: dict[str, Any], fitted: dict[str, Any]) -> str | None:
    """The first difference of a saved normalizer from the one fitted on the task's data, or None."""
    if saved.get("kind") != fitted["kind"]:
        return f"kind is {saved.get('kind')!r}, the data gives {fitted['kind']!r}"
    for key, value in fitted.items():
        if key == "kind":
            continue
        if key not in saved:
            return f"{key} is absent"
        have, want = np.asarray(saved[key], dtype=np.float64), np.asarray(value, dtype=np.float64)
        if have.shape != want.shape:
            return f"{key} has {have.size} dimensions, the data has {want.size}"
        far = np.flatnonzero(~np.isclose(have, want, rtol=NORMALIZER_RTOL, atol=0.0))
        if far.size:
            i = int(far[0])
            return f"{key}[{i}] is {have[i]:.6g}, the data gives {want[i]:.6g} ({far.size} of {want.size} differ)"
    return None


def check_seed(params: Params, task: TaskParams, folder: Path, seed: int, root: Path) -> dict[str, Any]:
    """Check the model of training seed ``seed`` in ``folder`` against ``task`` and its data; :class:`StageError`
    naming the first problem. Returns what the import records of it."""
    where = f"pretrained.{task.name}"
    src = folder / seed_name(seed)
    if not src.is_dir():
        held = sorted(p.name for p in folder.iterdir() if p.is_dir() and p.name.startswith("seed"))
        raise StageError(
            f"{where}: {folder} has no {seed_name(seed)}/ for training seed {seed} of seeds {list(params.seeds)} "
            f"(it holds {held or 'no seed<s>/ folder'})"
        )
    missing = [name for name in BUNDLE_FILES if not (src / name).is_file()]
    if missing:
        raise StageError(f"{where}: {src} is not a model folder: no {', '.join(missing)}")
    config = read_json(src / "config.json")
    if not isinstance(config, dict):
        raise StageError(f"{where}: {src.name}/config.json is not a JSON object of the model's settings")
    traj, expert = expert_training_data(task, root, seed)
    meta = traj.metadata
    shape = check_shape(config, task, meta["obs_dim"], meta["act_dim"])
    if shape:
        raise StageError(f"{where}: {src.name} does not have task {task.name}'s shape: {'; '.join(shape)}")
    try:
        load_bundle(src)
    except Exception as err:  # a truncated or foreign file: unpickling, EOF, shape and key errors alike
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise StageError(f"{where}: {src.name}'s weights do not load into task {task.name}'s model: {first}") from None
    fitted = fit_normalizer(get_family(task.family).normalizer_kind, joint_array(traj)).state_dict()
    problem = check_normalizer(read_json(src / "normalizer.json"), fitted)
    trained_on = config.get("data", {}).get("expert", {}).get("sha256")
    if problem:
        raise StageError(
            f"{where}: {src.name}/normalizer.json does not match the task's data {expert['path']}: {problem} "
            f"(trained on data {str(trained_on)[:12]}, this data is {str(expert['sha256'])[:12]})"
        )
    return {
        "source": str(src),
        "sha256": source_digest(src),
        "trained_on_sha256": trained_on,
        "data_sha256": expert["sha256"],
        "same_data": trained_on == expert["sha256"],
        "has_value": (src / "value").is_dir(),
    }


def run_import_model(params: Params, task_name: str, root: Path, device: torch.device, progress: bool = True) -> Path:
    """Stage ``import-model@<task>``: check every training seed's model in ``pretrained.<task>`` (nothing is written
    unless all pass), copy each to ``models/<task>/phase0/seed<s>`` and write ``phase0/import.json``. Families
    whose planner is value-guided get a seed's value function trained when its folder brings none."""
    task = params.resolve(task_name)
    folder = pretrained_folder(params, task.name, root)
    if not folder.is_dir():
        raise StageError(f"pretrained.{task.name}: {folder} is not a folder (it should hold seed<s>/ model folders)")
    family = get_family(task.family)
    logged = {"task": task.section("settings"), "pretrained": str(folder), "seeds": list(params.seeds)}
    with stage_run(task.name, "import-model", 0, logged, root) as run:
        seeds = {seed: check_seed(params, task, folder, seed, root) for seed in params.seeds}
        for seed in params.seeds:
            with atomic_dir(root / model_dir(task.name, 0, seed)) as tmp:
                shutil.copytree(folder / seed_name(seed), tmp, dirs_exist_ok=True)
        run.log_params({f"seed{seed}.sha256": entry["sha256"] for seed, entry in seeds.items()})
        run.log_metrics({f"seed{seed}.same_data": float(entry["same_data"]) for seed, entry in seeds.items()})
        summary = {"imported": True, "folder": str(folder), "seeds": {seed_name(s): e for s, e in seeds.items()}}
        out = root / phase_models_dir(task.name, 0)
        write_json(out / IMPORT_SUMMARY, summary)
    if family.uses_value_function:
        for seed, entry in seeds.items():
            if not entry["has_value"]:
                run_value(params, task.name, root, device, seed, progress=progress)
    return out
