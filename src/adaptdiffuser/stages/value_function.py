"""The learned value function that guides a task's planner (Diffuser's locomotion critic); the pretrain stage
trains it after the diffusion model, for families that use one."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from adaptdiffuser.checkpoint import ModelBundle, load_bundle
from adaptdiffuser.config import Params
from adaptdiffuser.config.tasks import TaskParams
from adaptdiffuser.config.value_settings import ValueSettings
from adaptdiffuser.data.returns import ValueWindowDataset
from adaptdiffuser.data.schema import Trajectories
from adaptdiffuser.data.windows import take_episodes
from adaptdiffuser.derived_seeds import derive_seed, training_seed
from adaptdiffuser.layout import model_dir, value_dir, value_resume_path
from adaptdiffuser.models.value_network import ValueNetwork
from adaptdiffuser.plots import save_loss_curve
from adaptdiffuser.stages.training_data import code_digest, expert_training_data, pretrain_config
from adaptdiffuser.tooling.run_records import stage_run
from adaptdiffuser.training import LogFn, fingerprint
from adaptdiffuser.value_training import heldout_r2, save_value, train_value

#: windows of the held-out episodes the value's R^2 is measured on
HELDOUT_WINDOWS = 4096


def split_heldout(traj: Trajectories, fraction: float, seed: int) -> tuple[Trajectories, Trajectories | None]:
    """The episodes to train the value on and the held-out ones (``round(fraction * n)`` of ``n``, at least one,
    drawn with ``seed``; at least one is trained on). ``fraction`` 0 or a single episode: nothing held out."""
    n = len(traj.episodes())
    k = min(n - 1, max(1, round(fraction * n))) if fraction > 0 else 0
    if k <= 0:
        return traj, None
    held = np.sort(np.random.default_rng(seed).choice(n, size=k, replace=False))
    return take_episodes(traj, np.setdiff1d(np.arange(n), held)), take_episodes(traj, held)


def fit_value(
    task: TaskParams,
    bundle: ModelBundle,
    traj: Trajectories,
    seed: int,
    device: torch.device,
    progress: bool = True,
    on_log: LogFn | None = None,
    resume_path: Path | None = None,
    run_id: str = "",
) -> tuple[ValueNetwork, dict[str, Any], list[tuple[int, float]]]:
    """Train training seed ``seed``'s value network of ``task`` on ``traj``'s windows, noised with ``bundle``'s
    diffusion schedule and scaled by its normalizer, less the held-out episodes (``value.holdout_fraction``) on
    which its R^2 is then measured. Returns the network, its fit (``episodes``, ``heldout_episodes``,
    ``training_windows``, ``parameters`` and, when episodes are held out, ``r2``, ``r2_t0``, ``windows``) and the
    logged losses. Only the bundle's schedule and normalizer are used, never its weights: the value function does
    not depend on the diffusion model it guides. ``resume_path`` and ``run_id``: as :func:`train_value`'s."""
    net_settings = task.settings.value_model
    settings = value_settings(task, seed)
    traj, heldout = split_heldout(traj, settings.holdout_fraction, derive_seed(settings.seed, 1))
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
    history = train_value(
        net, bundle.diffusion, dataset, settings, device, progress=progress, on_log=on_log,
        resume_path=resume_path, run_id=run_id,
    )  # fmt: skip
    fit: dict[str, Any] = {"episodes": len(traj.episodes()), "heldout_episodes": 0, "training_windows": len(dataset),
                           "parameters": sum(p.numel() for p in net.parameters())}  # fmt: skip
    if heldout is not None:
        held = ValueWindowDataset(
            heldout, task.diffusion.horizon, bundle.normalizer, settings.discount, settings.terminal_penalty
        )
        fit |= heldout_r2(net, bundle.diffusion, held, HELDOUT_WINDOWS, derive_seed(settings.seed, 2), device)
        fit["heldout_episodes"] = len(heldout.episodes())
    return net, fit, history


def value_run_id(task: TaskParams, logged: dict[str, Any], seed: int) -> str:
    """What tells a value training's resume state apart: its logged params (settings, network, data, seed, code),
    the diffusion schedule and model section it is built with, and the pretraining seed that draws the expert
    subset its normalizer is fitted on."""
    return fingerprint(logged, task.section("diffusion"), task.section("model"), pretrain_config(task, seed).seed)


def value_settings(task: TaskParams, seed: int) -> ValueSettings:
    """The task's value settings for training seed ``seed`` (its own seed derived from it)."""
    return task.settings.value.model_copy(update={"seed": training_seed(task.settings.value.seed, seed)})


def run_value(
    params: Params, task_name: str, root: Path, device: torch.device, seed: int, progress: bool = True
) -> Path:
    """Stage part ``value`` of ``pretrain@<task>``: :func:`fit_value` on training seed ``seed``'s phase-0 training
    data with its phase-0 model's schedule and normalizer (MLflow ``value_heldout_r2``, ``value_heldout_r2_t0``;
    ``heldout`` in the value's ``config.json``); write ``models/<task>/phase0/seed<s>/value``."""
    task = params.resolve(task_name)
    settings = value_settings(task, seed)
    bundle = load_bundle(root / model_dir(task.name, 0, seed), "cpu")
    traj, data = expert_training_data(task, root, seed)
    logged = {
        "value": settings.model_dump(),
        "value_model": task.settings.value_model.model_dump(),
        "data": {"expert": data},
        "seed": seed,
        "code": code_digest(root, task.name),
    }
    resume = root / value_resume_path(task.name, seed)
    resume.parent.mkdir(parents=True, exist_ok=True)
    with stage_run(task.name, "value", 0, logged, root, seed=seed) as run:
        net, fit, history = fit_value(
            task, bundle, traj, seed, device, progress,
            on_log=lambda step, loss: run.log_metric("value_loss", loss, step=step),
            resume_path=resume, run_id=value_run_id(task, logged, seed),
        )  # fmt: skip
        run.log_metrics({"windows": fit.pop("training_windows"), "parameters": fit.pop("parameters")})
        if fit["heldout_episodes"]:
            run.log_metrics({"value_heldout_r2": fit["r2"], "value_heldout_r2_t0": fit["r2_t0"]})
        out = root / value_dir(task.name, seed)
        info = {"settings": settings.model_dump(), "task": task.name, "data": data, "heldout": fit}
        save_value(out, net.cpu(), info)
        curve = out / "value_loss.png"  # written after the atomic folder exists
        save_loss_curve(history, curve)
        run.log_artifacts(str(out), artifact_path="value")
    return out
