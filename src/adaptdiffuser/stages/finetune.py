"""Stages ``finetune@phase<k>`` (continue phase k-1's model on expert plus selected synthetic data) and
``control@phase<k>`` (the same training on expert data only: the equal-compute control of phase k)."""

from __future__ import annotations

import shutil
from dataclasses import asdict, replace
from pathlib import Path

import torch

from adaptdiffuser.checkpoint import load_bundle, save_bundle
from adaptdiffuser.config import Params, PretrainParams, TaskParams
from adaptdiffuser.data.schema import read_trajectories
from adaptdiffuser.data.windows import MixedWindowDataset, WindowDataset
from adaptdiffuser.derived_seeds import derive_seed, training_seed
from adaptdiffuser.io import atomic_dir
from adaptdiffuser.layout import model_dir, phase_models_dir, phase_name, resume_path, selected_path
from adaptdiffuser.plots import save_loss_curve
from adaptdiffuser.stages.common import file_digest
from adaptdiffuser.stages.training_data import code_digest, expert_training_data
from adaptdiffuser.tooling.run_records import stage_run
from adaptdiffuser.training import carried_optimizer, fingerprint, train


def finetune_config(params: Params, task: TaskParams, phase: int, seed: int) -> PretrainParams:
    """Training settings of a fine-tuning phase for training seed ``seed``: pretraining's, for
    ``finetune.steps_fraction`` of its steps, with a seed derived from the phase and the training seed, and the
    EMA updated from the first step (it continues phase k-1's)."""
    f = params.phase(phase).finetune
    steps = max(1, round(f.steps_fraction * task.pretrain.steps))
    return replace(task.pretrain, steps=steps, seed=training_seed(derive_seed(f.seed, phase), seed), ema_start=0)


def run_finetune(
    params: Params,
    task_name: str,
    root: Path,
    phase: int,
    device: torch.device,
    progress: bool = True,
    control: bool = False,
) -> Path:
    """Stage ``finetune@phase<k>`` (or ``control@phase<k>``): :func:`finetune_seed` for every training seed;
    returns the phase's models folder."""
    for seed in params.seeds:
        finetune_seed(params, task_name, root, phase, device, seed, progress, control)
    for seed in params.seeds:  # kept until every seed is saved: a stage killed on seed s skips the seeds before it
        (root / resume_path(task_name, phase, seed, control)).unlink(missing_ok=True)
    return root / phase_models_dir(task_name, phase, control)


def finetune_seed(
    params: Params,
    task_name: str,
    root: Path,
    phase: int,
    device: torch.device,
    seed: int,
    progress: bool = True,
    control: bool = False,
) -> Path:
    """Start from phase k-1's weights, EMA and normalizer; train on the expert data mixed with the data selected
    in phase k and its ancestors (``finetune.expert_weight`` of each batch is expert), all of training seed
    ``seed``; write ``models/<task>/phase<k>/seed<s>``. With ``control``, train on expert data only, with the same
    steps, seed and settings, into ``models/<task>/phase<k>-control/seed<s>``: the difference between the two is
    the synthetic data."""
    task = params.resolve(task_name)
    cfg = params.phase(phase)
    source = model_dir(task.name, cfg.previous, seed)
    bundle = load_bundle(root / source, device)
    expert, expert_info = expert_training_data(task, root, seed)
    synthetic_info = {}
    parts = [WindowDataset(expert, task.diffusion.horizon, bundle.normalizer)]
    for j in [] if control else params.lineage(phase):
        path = root / selected_path(task.name, j, seed)
        selected = read_trajectories(path, env=task.name)
        if len(selected) == 0:  # that phase's discriminator kept nothing: no synthetic windows from it
            continue
        parts.append(WindowDataset(selected, task.diffusion.horizon, bundle.normalizer))
        synthetic_info[f"phase{j}"] = {"path": str(selected_path(task.name, j, seed)), "sha256": file_digest(path)}
    # with no synthetic data at all, the phase trains exactly as its control does
    w = 1.0 if len(parts) == 1 else cfg.finetune.expert_weight
    synthetic_share = (1.0 - w) / max(1, len(parts) - 1)
    dataset = MixedWindowDataset(parts, [w] + [synthetic_share] * (len(parts) - 1))
    train_cfg = finetune_config(params, task, phase, seed)
    logged = {
        "finetune": asdict(cfg.finetune) | {"control": control},
        "train": asdict(train_cfg),
        "model": {"path": str(source), "phase": cfg.previous, "sha256": file_digest(root / source / "model.pt")},
        "data": {"expert": expert_info, "synthetic": synthetic_info},
        "compile": {"training": params.compile.training},
        "seed": seed,
        "code": code_digest(root, task.name),
    }
    stage = "control" if control else "finetune"
    with stage_run(task.name, stage, phase, logged, root, seed=seed) as run:
        run.log_dataset(root / expert_info["path"], expert_info["sha256"], "training", expert_info["path"])
        for name, info in synthetic_info.items():
            run.log_dataset(root / info["path"], info["sha256"], f"synthetic-{name}", info["path"])
        run.log_metrics({f"windows.{name}": len(p) for name, p in zip(["expert", *synthetic_info], parts, strict=True)})
        resume = root / resume_path(task.name, phase, seed, control)
        resume.parent.mkdir(parents=True, exist_ok=True)
        history = train(
            bundle,
            dataset,
            train_cfg,
            device,
            resume_path=resume,
            run_id=fingerprint(logged, bundle.config),
            progress=progress,
            on_log=lambda step, loss: run.log_metric("train_loss", loss, step=step),
            optimizer_state=carried_optimizer(bundle, cfg.finetune.optimizer, str(source)),
            compiled=params.compile.training,
        )
        bundle.config = {
            **bundle.config,
            "phase": phase,
            "previous": cfg.previous,
            "finetune": asdict(cfg.finetune),
            "control": control,
            "seed": seed,
            "data": logged["data"],
        }
        out = root / model_dir(task.name, phase, seed, control)
        save_bundle(out, bundle)
        if (root / source / "value").is_dir():  # the planner's value function travels with the model (not retrained)
            with atomic_dir(out / "value") as tmp:
                shutil.copytree(root / source / "value", tmp, dirs_exist_ok=True)
        save_loss_curve(history, out / "train_loss.png")
        run.log_artifacts(str(out), artifact_path="checkpoint")
        label, primary = phase_name(phase, control), seed == params.seeds[0]
        run.log_model(bundle.ema, out, task.name, label, seed, primary, {"stage": stage, "previous": cfg.previous})
    return out
