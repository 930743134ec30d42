"""Score and evaluation time of a value-guided (locomotion) planner replanning from pure noise against replanning
warm-started from its last plan, side by side on the same episodes (printed, never asserted).

Every decision after an episode's first can start from the plan executed last, shifted by one step and noised to
diffusion step K (``guide.warm_start_step``), so its chain runs K + 1 denoising steps instead of all of them. For
each K of ``--warm-steps`` the task's phase-k model of one training seed is evaluated under the task's protocol on
``--episodes`` episodes from ``--seed`` (a validation seed by default, not ``evaluate.seed``: choose on it, then
confirm once on the evaluation seed), with the gain over replanning from pure noise paired per episode.

    python benchmarks/compare_warm_start.py WORKSPACE [--task hopper-medium] [--warm-steps 2 4 8]
        [--seed 7] [--episodes 10] [--phase 0] [--training-seed 0]

WORKSPACE is a pipeline folder after `dvc repro` (its params.yaml, models/, value function and reference.json).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from trained_workspace import add_workspace_args, load_trained

from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.evaluation import normalized_score, paired_gain, run_episodes, standard_error
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.planning import Planner


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_workspace_args(parser)
    parser.add_argument("--warm-steps", type=int, nargs="+", default=[2, 4, 8])
    args = parser.parse_args()
    ws = load_trained(args)
    base = ws.task()
    family = get_family(base.family)
    ref, files, ev = ws.reference(), ws.files(), base.evaluate
    print(f"{ws.name} phase {args.phase} (training seed {args.training_seed}), {ev.episodes} episodes from seed "
          f"{args.seed}, {base.planner.sampler} {base.planner.sampler_steps}, torch threads "
          f"{torch.get_num_threads()}")  # fmt: skip

    scores: dict[int | None, np.ndarray] = {}
    for warm in [None, *args.warm_steps]:
        task = ws.task("guide.warm_start_step", warm)
        planner = Planner(ws.bundle, make_sampler(task.planner.sampler, task.planner.sampler_steps), ws.device)
        start = time.perf_counter()
        result = run_episodes(
            lambda task=task: family.make_simulator(task),
            family.controller(task, planner, files, ws.device),
            ev.episodes,
            ev.seed,
            ev.batch_size,
            progress=False,
        )
        elapsed = time.perf_counter() - start
        scores[warm] = normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"])
        label = "pure noise" if warm is None else f"warm start at step {warm}"
        batches = [result.lengths[i : i + ev.batch_size] for i in range(0, ev.episodes, ev.batch_size)]
        per_step_ms = 1000 * elapsed / sum(max(b) for b in batches)  # a batch decides until its longest episode ends
        print(f"{label:>24}: score {scores[warm].mean():6.1f} +- {standard_error(scores[warm]):4.1f}, mean length "
              f"{np.mean(result.lengths):6.1f}, evaluation {elapsed:6.1f} s ({per_step_ms:.0f} ms per batched "
              f"decision)", flush=True)  # fmt: skip
    print("gain over pure noise, paired per episode:")
    for warm in args.warm_steps:
        gain = paired_gain(scores[warm], scores[None])
        print(f"  warm start at step {warm}: {gain['gain_mean']:+6.1f} +- {gain['gain_stderr']:4.1f}")


if __name__ == "__main__":
    main()
