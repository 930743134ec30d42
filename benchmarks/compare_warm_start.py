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
from pathlib import Path

import numpy as np
import torch
import yaml

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import params_from_dict, set_dotted
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.evaluation import normalized_score, paired_gain, run_episodes, standard_error
from adaptdiffuser.families.base import TaskFiles
from adaptdiffuser.families.registry import get_family
from adaptdiffuser.io import read_json
from adaptdiffuser.planning import Planner
from adaptdiffuser.stages.common import model_dir, reference_path, resolve_device


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--task", default=None, help="a value-guided task of params (default: the evolved task)")
    parser.add_argument("--warm-steps", type=int, nargs="+", default=[2, 4, 8])
    parser.add_argument("--seed", type=int, default=7, help="episode seed (default 7: validation, not evaluation)")
    parser.add_argument("--episodes", type=int, default=None, help="default: the task's evaluate.episodes")
    parser.add_argument("--phase", type=int, default=0)
    parser.add_argument("--training-seed", type=int, default=0)
    parser.add_argument("--device", default="auto")
    args = parser.parse_args()
    root = args.workspace.resolve()
    raw = yaml.safe_load((root / "params.yaml").read_text())
    name = args.task or raw.get("evolve") or raw["tasks"][0]
    raw = set_dotted(raw, f"task.{name}.evaluate.seed", args.seed)
    if args.episodes is not None:
        raw = set_dotted(raw, f"task.{name}.evaluate.episodes", args.episodes)
    device = resolve_device(args.device)
    base = params_from_dict(raw).resolve(name)
    family = get_family(base.family)
    model = model_dir(name, args.phase, args.training_seed)
    bundle = load_bundle(root / model, device)
    ref = read_json(root / reference_path(name), f"reference scores of {name}")
    files = TaskFiles(root, name, model, args.training_seed)
    ev = base.evaluate
    print(f"{name} phase {args.phase} (training seed {args.training_seed}), {ev.episodes} episodes from seed "
          f"{args.seed}, {base.planner.sampler} {base.planner.sampler_steps}, torch threads "
          f"{torch.get_num_threads()}")  # fmt: skip

    scores: dict[int | None, np.ndarray] = {}
    for warm in [None, *args.warm_steps]:
        task = params_from_dict(set_dotted(raw, f"task.{name}.guide.warm_start_step", warm)).resolve(name)
        planner = Planner(bundle, make_sampler(task.planner.sampler, task.planner.sampler_steps), device)
        start = time.perf_counter()
        result = run_episodes(
            lambda task=task: family.make_simulator(task),
            family.controller(task, planner, files, device),
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
