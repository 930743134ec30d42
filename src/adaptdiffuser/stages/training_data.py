"""What every training stage of a task starts from: the expert episodes a training seed trains on, the
pretraining settings of that seed (fine-tuning and the control reuse them) and the digest of the task's code."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from adaptdiffuser.config import PretrainParams, TaskParams
from adaptdiffuser.data.schema import Trajectories, read_trajectories
from adaptdiffuser.data.windows import subset_episodes
from adaptdiffuser.derived_seeds import training_seed
from adaptdiffuser.layout import dataset_path
from adaptdiffuser.stages.common import file_digest
from adaptdiffuser.tooling.code_fingerprint import fingerprint_path


def pretrain_config(task: TaskParams, seed: int) -> PretrainParams:
    """Pretraining's settings for training seed ``seed`` (its seed derived from ``pretrain.seed`` and ``seed``)."""
    return replace(task.pretrain, seed=training_seed(task.pretrain.seed, seed))


def expert_training_data(task: TaskParams, root: Path, seed: int) -> tuple[Trajectories, dict[str, str | float]]:
    """The dataset episodes the models of training seed ``seed`` train on (``pretrain.expert_fraction`` of them,
    chosen with that seed's pretraining seed, so every phase sees the same subset) and how to name them in logs."""
    data_path = root / dataset_path(task.name)
    traj = read_trajectories(data_path, env=task.name)
    fraction = task.pretrain.expert_fraction
    subset = subset_episodes(traj, fraction, np.random.default_rng(pretrain_config(task, seed).seed))
    return subset, {"path": str(dataset_path(task.name)), "sha256": file_digest(data_path), "fraction": fraction}


def code_digest(root: Path, task: str) -> str | None:
    """SHA-256 of the task's code fingerprint (``code/<task>.json``, written by its ``code`` stage), or None where
    there is none (a library call outside the pipeline): training tells its own resume states by it, so that a
    state written by other code is not taken up."""
    path = root / fingerprint_path(task)
    return file_digest(path) if path.is_file() else None
