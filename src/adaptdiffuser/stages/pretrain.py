"""Stage ``pretrain`` (phase 0): the Diffuser baseline, trained on expert data."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import mlflow
import numpy as np
import torch

from adaptdiffuser.checkpoint import make_bundle, save_bundle
from adaptdiffuser.config import Params
from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.data.schema import Trajectories, read_trajectories
from adaptdiffuser.data.windows import WindowDataset, joint_array, subset_episodes
from adaptdiffuser.plots import save_loss_curve
from adaptdiffuser.stages.common import EXPERT_DATA, file_digest, model_dir
from adaptdiffuser.tracking import stage_run
from adaptdiffuser.training import fingerprint, train


def expert_training_data(params: Params, root: Path) -> tuple[Trajectories, dict[str, str | float]]:
    """The expert episodes the models train on (``pretrain.expert_fraction`` of them, chosen with
    ``pretrain.seed``, so every phase sees the same subset) and how to name them in logs."""
    data_path = root / EXPERT_DATA
    traj = read_trajectories(data_path)
    fraction = params.pretrain.expert_fraction
    subset = subset_episodes(traj, fraction, np.random.default_rng(params.pretrain.seed))
    return subset, {"path": str(EXPERT_DATA), "sha256": file_digest(data_path), "fraction": fraction}


def run_pretrain(params: Params, root: Path, device: torch.device, progress: bool = True) -> Path:
    """Stage ``pretrain`` (phase 0, the Diffuser baseline): train on expert data, write ``models/phase0``."""
    traj, expert = expert_training_data(params, root)
    logged = {
        "model": params.section("model"),
        "diffusion": params.section("diffusion"),
        "pretrain": params.section("pretrain"),
        "data": {"expert": expert},
    }
    with stage_run(params.task, "pretrain", 0, logged, root):
        torch.manual_seed(params.pretrain.seed)
        normalizer = MinMaxNormalizer.fit(joint_array(traj))
        meta = traj.metadata
        bundle = make_bundle(
            params.model,
            params.diffusion,
            meta["obs_dim"],
            meta["act_dim"],
            normalizer,
            task=params.task,
            phase=0,
            pretrain=asdict(params.pretrain),
            data=logged["data"],
        )
        dataset = WindowDataset(traj, params.diffusion.horizon, normalizer)
        mlflow.log_metrics(
            {
                "windows": len(dataset),
                "expert_episodes": len(traj.episodes()),
                "parameters": sum(p.numel() for p in bundle.diffusion.parameters()),
            }
        )
        resume = root / "models" / ".resume" / "phase0.pt"
        resume.parent.mkdir(parents=True, exist_ok=True)
        history = train(
            bundle,
            dataset,
            params.pretrain,
            device,
            resume_path=resume,
            run_id=fingerprint(logged),
            progress=progress,
            on_log=lambda step, loss: mlflow.log_metric("train_loss", loss, step=step),
        )
        out = root / model_dir(0)
        save_bundle(out, bundle)
        curve = out / "train_loss.png"
        save_loss_curve(history, curve)
        mlflow.log_artifacts(str(out), artifact_path="checkpoint")  # weights, config and the loss curve
        resume.unlink(missing_ok=True)
    return out
