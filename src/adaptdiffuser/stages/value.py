"""The learned value function that guides a task's planner (Diffuser's locomotion critic); the pretrain stage
trains it after the diffusion model, for families that use one."""

from __future__ import annotations

from pathlib import Path

import mlflow
import torch

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import Params
from adaptdiffuser.data.returns import ValueWindowDataset
from adaptdiffuser.models.value import ValueNetwork
from adaptdiffuser.plots import save_loss_curve
from adaptdiffuser.seeding import training_seed
from adaptdiffuser.stages.common import model_dir, value_dir
from adaptdiffuser.stages.pretrain import expert_training_data
from adaptdiffuser.tracking import stage_run
from adaptdiffuser.value_training import save_value, train_value


def run_value(
    params: Params, task_name: str, root: Path, device: torch.device, seed: int, progress: bool = True
) -> Path:
    """Regress the discounted return-to-go of training seed ``seed``'s phase-0 training windows, noised with its
    diffusion schedule and scaled by its normalizer; write ``models/<task>/phase0/seed<s>/value``."""
    task = params.resolve(task_name)
    net_settings = task.settings.value_model
    settings = task.settings.value.model_copy(update={"seed": training_seed(task.settings.value.seed, seed)})
    bundle = load_bundle(root / model_dir(task.name, 0, seed), "cpu")
    traj, data = expert_training_data(task, root, seed)
    logged = {
        "value": settings.model_dump(),
        "value_model": net_settings.model_dump(),
        "data": {"expert": data},
        "seed": seed,
    }
    with stage_run(task.name, "value", 0, logged, root, seed=seed):
        dataset = ValueWindowDataset(
            traj, task.diffusion.horizon, bundle.normalizer, settings.discount, settings.terminal_penalty
        )
        torch.manual_seed(settings.seed)
        net = ValueNetwork(
            bundle.diffusion.transition_dim,
            task.diffusion.horizon,
            dim=net_settings.dim,
            dim_mults=tuple(net_settings.dim_mults),
            kernel_size=task.model.kernel_size,
        )
        mlflow.log_metrics({"windows": len(dataset), "parameters": sum(p.numel() for p in net.parameters())})
        history = train_value(
            net,
            bundle.diffusion,
            dataset,
            settings,
            device,
            progress=progress,
            on_log=lambda step, loss: mlflow.log_metric("value_loss", loss, step=step),
        )
        out = root / value_dir(task.name, seed)
        save_value(out, net.cpu(), {"settings": settings.model_dump(), "task": task.name, "data": data})
        curve = out / "value_loss.png"  # written after the atomic folder exists
        save_loss_curve(history, curve)
        mlflow.log_artifacts(str(out), artifact_path="value")
    return out
