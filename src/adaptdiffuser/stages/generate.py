"""Stage ``generate@phase<k>``: goal-conditioned plans for many random tasks, sampled from phase k-1's model."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import mlflow
import numpy as np
import torch

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import Params
from adaptdiffuser.data.schema import write_trajectories
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.evolution.discriminator import planned_trajectory
from adaptdiffuser.evolution.generate import generate_plans, task_trajectories
from adaptdiffuser.families.maze2d.tasks import add_coins, sample_navigation_tasks
from adaptdiffuser.families.registry import get_family
from adaptdiffuser.planning import Planner
from adaptdiffuser.seeding import derive_seed
from adaptdiffuser.stages.common import generated_path, model_dir
from adaptdiffuser.tracking import stage_run


def run_generate(
    params: Params, task_name: str, root: Path, phase: int, device: torch.device, progress: bool = True
) -> dict:
    """Sample one plan per random (start, goal) task with the model of the phase this one starts from; write
    the plans (planned states and actions, planned reward) to ``data/<task>/phase<k>/generated.parquet``."""
    task = params.resolve(task_name)
    cfg = params.phase(phase)
    g = cfg.generate
    source = model_dir(task.name, cfg.previous)
    bundle = load_bundle(root / source, device)
    seed = derive_seed(g.seed, phase)
    logged = {"generate": asdict(g), "alpha": params.alpha, "model": {"path": str(source)}}
    with stage_run(task.name, "generate", phase, logged, root):
        env = get_family(task.family).make_simulator(task)
        rng = np.random.default_rng(seed)
        tasks = sample_navigation_tasks(env, g.tasks, rng, g.cell_spread)
        if g.coin_fraction > 0:
            tasks = add_coins(env, tasks, g.coin_fraction, rng)
        planner = Planner(bundle, make_sampler(g.sampler, g.sampler_steps), device)
        plans = generate_plans(planner, tasks, g.batch_size, seed, alpha=params.alpha, progress=progress)
        act_dim = planner.act_dim
        planned = [
            planned_trajectory(env, p[:, act_dim:], p[:, :act_dim], goal)
            for p, goal in zip(plans, tasks.goals, strict=True)
        ]
        traj = task_trajectories(
            planned,
            tasks,
            np.arange(len(tasks)),
            task.name,
            {"stage": "generate", "phase": phase, "model": str(source), "alpha": params.alpha, **asdict(g)},
        )
        out = root / generated_path(task.name, phase)
        out.parent.mkdir(parents=True, exist_ok=True)
        write_trajectories(out, traj)
        stats = {
            "generated": len(tasks),
            "coin_tasks": int(tasks.has_coin().sum()),
            "planned_reach_rate": float(np.mean([t.steps_to_goal >= 0 for t in planned])),
            "planned_return_mean": float(np.mean([t.total_reward for t in planned])),
        }
        mlflow.log_metrics(stats)
    return stats
