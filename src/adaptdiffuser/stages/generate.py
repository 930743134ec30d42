"""Stage ``generate@phase<k>``: synthetic plans for many tasks the family samples, from phase k-1's model."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import GenerateParams, Params
from adaptdiffuser.contract import TaskFiles
from adaptdiffuser.data.schema import write_trajectories
from adaptdiffuser.derived_seeds import derive_seed, training_seed
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.layout import generated_path, model_dir
from adaptdiffuser.planning import Planner
from adaptdiffuser.tooling.run_records import stage_run


def run_generate(
    params: Params, task_name: str, root: Path, phase: int, device: torch.device, progress: bool = True
) -> dict[int, dict]:
    """Stage ``generate@phase<k>``: :func:`generate_seed` for every training seed; each seed's statistics."""
    return {seed: generate_seed(params, task_name, root, phase, device, seed, progress) for seed in params.seeds}


def generation_seed(cfg: GenerateParams, phase: int, seed: int) -> int:
    """The seed phase ``phase``'s generation draws its tasks and noise from for training seed ``seed``."""
    return training_seed(derive_seed(cfg.seed, phase), seed)


def generate_seed(
    params: Params, task_name: str, root: Path, phase: int, device: torch.device, seed: int, progress: bool = True
) -> dict:
    """Sample the family's generation tasks with training seed ``seed``'s model of the phase this one starts from
    (guided as the family does it); write the plans to ``data/<task>/phase<k>/generated/seed<s>.parquet``."""
    task = params.resolve(task_name)
    cfg = params.phase(phase)
    g = cfg.generate
    source = model_dir(task.name, cfg.previous, seed)
    bundle = load_bundle(root / source, device)
    seed_of_generation = generation_seed(g, phase, seed)
    logged = {
        "generate": asdict(g),
        "alpha": params.alpha,
        "model": {"path": str(source)},
        "compile": {"sampling": params.compile.sampling},
        "seed": seed,
    }
    generator = {
        "stage": "generate",
        "phase": phase,
        "training_seed": seed,
        "model": str(source),
        "alpha": params.alpha,
        **asdict(g),
    }
    with stage_run(task.name, "generate", phase, logged, root, seed=seed) as run:
        planner = Planner(bundle, make_sampler(g.sampler, g.sampler_steps), device, params.compile.sampling)
        files = TaskFiles(root, task.name, source, seed)
        family = get_family(task.family)
        traj, stats = family.generate(task, planner, files, g, params.alpha, seed_of_generation, generator, progress)
        out = root / generated_path(task.name, phase, seed)
        out.parent.mkdir(parents=True, exist_ok=True)
        write_trajectories(out, traj)
        run.log_metrics(stats)
    return stats
