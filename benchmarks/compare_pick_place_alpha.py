"""KUKA pick-and-place scores of one trained planner at several guidance scales, on validation episodes (printed,
never asserted): how to choose ``task.<name>.pick_place.alpha`` without looking at the evaluation episodes.

For each alpha, the task's phase-k model of one training seed runs the pick-and-place evaluation of every setup on
``--episodes`` episodes from ``--seed`` (default 7: a validation seed, not ``pick_place.seed``).

    python benchmarks/compare_pick_place_alpha.py WORKSPACE [--alphas 0 1 10 100] [--seed 7] [--episodes 20]
        [--phase 0] [--training-seed 0]

WORKSPACE is a pipeline folder holding a trained KUKA model (after `dvc repro` of the quick-kuka profile).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import yaml

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import params_from_dict, set_dotted
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.families.registry import get_family
from adaptdiffuser.planning import Planner
from adaptdiffuser.stages.common import model_dir, resolve_device


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--task", default="kuka-stacking")
    parser.add_argument("--alphas", type=float, nargs="+", default=[0.0, 1.0, 10.0, 100.0])
    parser.add_argument("--seed", type=int, default=7, help="episode seed (default 7: validation, not evaluation)")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--phase", type=int, default=0)
    parser.add_argument("--training-seed", type=int, default=0)
    parser.add_argument("--device", default="auto")
    args = parser.parse_args()
    root = args.workspace.resolve()
    raw = yaml.safe_load((root / "params.yaml").read_text())
    raw = set_dotted(raw, f"task.{args.task}.pick_place.seed", args.seed)
    raw = set_dotted(raw, f"task.{args.task}.pick_place.episodes", args.episodes)
    device = resolve_device(args.device)
    base = params_from_dict(raw).resolve(args.task)
    bundle = load_bundle(root / model_dir(args.task, args.phase, args.training_seed), device)
    planner = Planner(bundle, make_sampler(base.planner.sampler, base.planner.sampler_steps), device)
    family = get_family(base.family)
    print(
        f"{args.task} phase {args.phase}, training seed {args.training_seed}: {args.episodes} episodes per setup "
        f"from seed {args.seed}"
    )
    for alpha in args.alphas:
        task = params_from_dict(set_dotted(raw, f"task.{args.task}.pick_place.alpha", alpha)).resolve(args.task)
        start = time.perf_counter()
        metrics = family.extra_evaluations(task, planner, progress=False)
        scores = "  ".join(
            f"setup {s}: {metrics[f'pick_place_setup{s}_score_mean']:.1f} +- "
            f"{metrics[f'pick_place_setup{s}_score_stderr']:.1f}"
            for s in task.settings.pick_place.setups
        )
        print(f"alpha {alpha:g}: {scores}  ({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
