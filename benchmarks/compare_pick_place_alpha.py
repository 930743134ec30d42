"""KUKA pick-and-place scores of one trained planner at several guidance scales, on validation episodes (printed,
never asserted): how to choose ``alpha`` for KUKA without looking at the evaluation episodes.

For each alpha, the task's phase-k model of one training seed runs the pick-and-place evaluation of every setup on
``--episodes`` episodes from ``--seed`` (default 7: a validation seed, not ``pick_place.seed``).

    python benchmarks/compare_pick_place_alpha.py WORKSPACE [--alphas 0 1 10 100] [--seed 7] [--episodes 20]
        [--phase 0] [--training-seed 0]

WORKSPACE is a pipeline folder holding a trained KUKA model (after `dvc repro` of the quick-kuka profile).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from trained_workspace import add_workspace_args, load_trained

from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.planning import Planner


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_workspace_args(parser, task="kuka-stacking", episodes=20)
    parser.add_argument("--alphas", type=float, nargs="+", default=[0.0, 1.0, 10.0, 100.0])
    args = parser.parse_args()
    ws = load_trained(args, episodes_section="pick_place")
    base = ws.task()
    planner = Planner(ws.bundle, make_sampler(base.planner.sampler, base.planner.sampler_steps), ws.device)
    family = get_family(base.family)
    print(
        f"{args.task} phase {args.phase}, training seed {args.training_seed}: {args.episodes} episodes per setup "
        f"from seed {args.seed}"
    )
    ref = ws.reference()
    for alpha in args.alphas:
        start = time.perf_counter()
        with tempfile.TemporaryDirectory() as pictures:
            metrics = family.evaluate_unseen(base, planner, alpha, ref, Path(pictures), "", progress=False)
        scores = "  ".join(
            f"setup {s}: {metrics[f'setup{s}_score_mean']:.1f} +- {metrics[f'setup{s}_score_stderr']:.1f}"
            for s in base.settings.pick_place.setups
        )
        print(f"alpha {alpha:g}: {scores}  ({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
