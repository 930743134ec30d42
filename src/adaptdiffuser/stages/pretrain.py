"""Stage ``pretrain`` (phase 0): the Diffuser baseline, trained on expert data."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch

from adaptdiffuser.checkpoint import ModelBundle, make_bundle, save_bundle
from adaptdiffuser.config import Params, PretrainParams, TaskParams
from adaptdiffuser.data.normalizer import fit_normalizer
from adaptdiffuser.data.schema import Trajectories
from adaptdiffuser.data.windows import WindowDataset, joint_array
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.layout import model_dir, phase_models_dir, resume_path, value_resume_path
from adaptdiffuser.plots import save_loss_curve
from adaptdiffuser.stages.training_data import code_digest, expert_training_data, pretrain_config
from adaptdiffuser.stages.value_function import run_value
from adaptdiffuser.tooling.run_records import stage_run
from adaptdiffuser.training import fingerprint, train


def run_pretrain(params: Params, task_name: str, root: Path, device: torch.device, progress: bool = True) -> Path:
    """Stage ``pretrain@<task>`` (phase 0, the Diffuser baseline): for every training seed of ``seeds``, train on
    the task's dataset and write ``models/<task>/phase0/seed<s>``; the family chooses the normalizer and which
    plan steps are inpainted. Families whose planner is value-guided get each seed's value function trained next,
    into ``models/<task>/phase0/seed<s>/value``."""
    for seed in params.seeds:
        pretrain_seed(params, task_name, root, device, seed, progress)
    for seed in params.seeds:  # kept until every seed is saved: a stage killed on seed s skips the seeds before it
        (root / resume_path(task_name, 0, seed)).unlink(missing_ok=True)
        (root / value_resume_path(task_name, seed)).unlink(missing_ok=True)
    return root / phase_models_dir(task_name, 0)


def phase0_model(
    task: TaskParams, traj: Trajectories, train_cfg: PretrainParams, data: dict, seed: int
) -> tuple[ModelBundle, WindowDataset]:
    """A fresh phase-0 model of ``task`` for training seed ``seed`` (torch seeded with ``train_cfg.seed``; the
    family's normalizer fitted to ``traj``; ``data`` names the training data in its config) and the training
    windows of ``traj``."""
    family = get_family(task.family)
    torch.manual_seed(train_cfg.seed)
    normalizer = fit_normalizer(family.normalizer_kind, joint_array(traj))
    meta = traj.metadata
    bundle = make_bundle(
        task.model,
        task.diffusion,
        meta["obs_dim"],
        meta["act_dim"],
        normalizer,
        task=task.name,
        family=task.family,
        conditioning=family.conditioning,
        phase=0,
        seed=seed,
        pretrain=asdict(train_cfg),
        data=data,
    )
    return bundle, WindowDataset(traj, task.diffusion.horizon, normalizer)


def pretrain_seed(
    params: Params, task_name: str, root: Path, device: torch.device, seed: int, progress: bool = True
) -> Path:
    """Phase 0 for one training seed: ``models/<task>/phase0/seed<s>`` (and its value function)."""
    task = params.resolve(task_name)
    family = get_family(task.family)
    traj, expert = expert_training_data(task, root, seed)
    train_cfg = pretrain_config(task, seed)
    logged = {
        "model": task.section("model"),
        "diffusion": task.section("diffusion"),
        "pretrain": asdict(train_cfg),
        "data": {"expert": expert},
        "compile": {"training": params.compile.training},
        "seed": seed,
        "code": code_digest(root, task.name),
    }
    with stage_run(task.name, "pretrain", 0, logged, root, seed=seed) as run:
        run.log_dataset(root / expert["path"], expert["sha256"], "training", expert["path"])
        bundle, dataset = phase0_model(task, traj, train_cfg, logged["data"], seed)
        run.log_metrics(
            {
                "windows": len(dataset),
                "expert_episodes": len(traj.episodes()),
                "parameters": sum(p.numel() for p in bundle.diffusion.parameters()),
            }
        )
        resume = root / resume_path(task.name, 0, seed)
        resume.parent.mkdir(parents=True, exist_ok=True)
        history = train(
            bundle,
            dataset,
            train_cfg,
            device,
            resume_path=resume,
            run_id=fingerprint(logged),
            progress=progress,
            on_log=lambda step, loss: run.log_metric("train_loss", loss, step=step),
            compiled=params.compile.training,
        )
        out = root / model_dir(task.name, 0, seed)
        save_bundle(out, bundle)
        curve = out / "train_loss.png"
        save_loss_curve(history, curve)
        run.log_artifacts(str(out), artifact_path="checkpoint")  # weights, config and the loss curve
        run.log_model(bundle.ema, out, task.name, "phase0", seed, seed == params.seeds[0], {"stage": "pretrain"})
    if family.uses_value_function:
        run_value(params, task.name, root, device, seed, progress=progress)
    return out
