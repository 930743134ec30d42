"""How smooth a trained model's plans are against its own dataset (printed and written, never asserted): a planner
whose planned states jitter from step to step where the real ones glide plans trajectories no simulator follows.

For each training seed, ``--starts`` windows of one horizon are drawn from the task's dataset (seeded by
``--seed``, whole windows inside one episode); the model plans from each window's first state, unguided, with the
full sampler chain from pure noise (one plan per start). Per observation dimension, in the normalizer's units:

* roughness: mean |second difference| over the plan's steps, plan against the dataset's windows (ratio > 1: the
  plan is rougher than the real trajectories);
* lag-1 autocorrelation of the steps (first differences): real positions move on smoothly (near +1), white error
  on a smooth signal gives about -0.5.

    python benchmarks/plan_smoothness.py WORKSPACE [--task walker2d-medium] [--phase 0] [--training-seeds 0 1 2]
        [--model DIR] [--starts 48] [--seed 0] [--out FILE]

WORKSPACE is a pipeline folder after `dvc repro` (its params.yaml, dataset and models).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import yaml

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import params_from_dict
from adaptdiffuser.data.schema import read_trajectories
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.io import atomic_path
from adaptdiffuser.layout import dataset_path, model_dir
from adaptdiffuser.planning import Planner


def dataset_windows(observations: np.ndarray, episode_id: np.ndarray, horizon: int, n: int, seed: int) -> np.ndarray:
    """``[n, horizon, obs_dim]`` windows of consecutive observations, each inside one episode."""
    rng = np.random.default_rng(seed)
    whole = np.flatnonzero(episode_id[: len(episode_id) - horizon + 1] == episode_id[horizon - 1 :])
    if len(whole) < n:
        raise SystemExit(f"only {len(whole)} windows of {horizon} steps lie inside one episode; ask fewer --starts")
    starts = rng.choice(whole, n, replace=False)
    return np.stack([observations[i : i + horizon] for i in starts])


def roughness(x: np.ndarray) -> np.ndarray:
    """Per dimension: mean |second difference| over steps of ``[batch, steps, dim]``."""
    return np.abs(x[:, 2:] - 2 * x[:, 1:-1] + x[:, :-2]).mean((0, 1))


def step_autocorrelation(x: np.ndarray) -> np.ndarray:
    """Per dimension: the lag-1 autocorrelation of the steps, mean over the batch."""
    d = np.diff(x, axis=1)
    d = d - d.mean(1, keepdims=True)
    return ((d[:, 1:] * d[:, :-1]).sum(1) / np.maximum((d * d).sum(1), 1e-12)).mean(0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--task", default=None, help="default: the evolved task, else the first")
    parser.add_argument("--phase", type=int, default=0)
    parser.add_argument("--training-seeds", type=int, nargs="+", default=[0])
    parser.add_argument(
        "--model",
        type=Path,
        default=None,
        help="a model folder to read instead (e.g. learning_curve.py --keep-model); one training seed",
    )
    parser.add_argument("--starts", type=int, default=48)
    parser.add_argument("--seed", type=int, default=0, help="seed of the windows drawn and of the plans' noise")
    parser.add_argument("--out", type=Path, default=None, help="default: plan_smoothness-<task>.json in WORKSPACE")
    args = parser.parse_args()
    if args.model is not None and len(args.training_seeds) != 1:
        parser.error("--model reads one model: give one --training-seeds")
    root = args.workspace.resolve()
    raw = yaml.safe_load((root / "params.yaml").read_text())
    name = args.task or raw.get("evolve") or raw["tasks"][0]
    task = params_from_dict(raw).resolve(name)
    data = read_trajectories(root / dataset_path(name))
    device = torch.device("cpu")
    record: dict = {
        "task": name,
        "phase": args.phase,
        "model": str(args.model or ""),
        "starts": args.starts,
        "seed": args.seed,
        "seeds": {},
    }
    for training_seed in args.training_seeds:
        bundle = load_bundle(args.model or root / model_dir(name, args.phase, training_seed), device)
        planner = Planner(bundle, make_sampler(task.planner.sampler, task.planner.sampler_steps), device)
        act = planner.act_dim
        windows = dataset_windows(data.observation, data.episode_id, planner.horizon, args.starts, args.seed)
        noise_seeds = np.arange(args.starts) + 1_000_003 * (args.seed + 1) + training_seed
        plans = planner.sample(windows[:, 0], None, noise_seeds).double().cpu().numpy()[:, :, act:]
        padded = np.concatenate([np.zeros(windows.shape[:2] + (act,)), windows], axis=-1)
        real = bundle.normalizer.normalize(padded)[:, :, act:]
        ratio = roughness(plans) / np.maximum(roughness(real), 1e-12)
        entry = {
            "roughness_ratio": ratio.round(3).tolist(),
            "step_autocorrelation_plan": step_autocorrelation(plans).round(3).tolist(),
            "step_autocorrelation_data": step_autocorrelation(real).round(3).tolist(),
        }
        record["seeds"][str(training_seed)] = entry
        which = args.model or f"phase {args.phase} seed {training_seed}"
        print(f"{name} {which}: roughness plan / data per observation dim "
              f"{np.round(ratio, 1).tolist()}")  # fmt: skip
        print(f"  lag-1 autocorrelation of steps, plan {np.round(entry['step_autocorrelation_plan'], 2).tolist()}")
        print(f"  lag-1 autocorrelation of steps, data {np.round(entry['step_autocorrelation_data'], 2).tolist()}")
    out = args.out or root / f"plan_smoothness-{name}.json"
    with atomic_path(out) as tmp:
        tmp.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
