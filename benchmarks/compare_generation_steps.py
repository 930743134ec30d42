"""Generation throughput against what the discriminator keeps, at several sampler step counts, on the same tasks
(printed, never asserted): fewer network calls per generated plan, if the kept data do not suffer.

For each DDIM step count of ``--steps``, phase k's generation (the family's tasks, guidance and seeds as the
pipeline draws them) runs from phase k-1's model of one training seed, then phase k's discriminator judges the
plans in the simulator. Printed per setting: plans per second, and the discriminator's report (generated, tracked,
kept, the kept plans' mean real return). Nothing is written to the workspace.

    python benchmarks/compare_generation_steps.py WORKSPACE [--task maze2d-umaze] [--steps 16 8 4] [--phase 1]
        [--training-seed 0]

WORKSPACE is a pipeline folder after `dvc repro` (its params.yaml and phase k-1's model).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import torch

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import load_params
from adaptdiffuser.contract import TaskFiles
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.layout import model_dir
from adaptdiffuser.planning import Planner
from adaptdiffuser.seeding import derive_seed, training_seed
from adaptdiffuser.stages.common import resolve_device


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--task", default=None, help="a task of params (default: the evolved task)")
    parser.add_argument("--steps", type=int, nargs="+", default=[16, 8, 4])
    parser.add_argument("--phase", type=int, default=1)
    parser.add_argument("--training-seed", type=int, default=0)
    parser.add_argument("--device", default="auto")
    args = parser.parse_args()
    root = args.workspace.resolve()
    params = load_params(root / "params.yaml")
    task = params.resolve(args.task or params.evolve)
    family = get_family(task.family)
    device = resolve_device(args.device)
    cfg = params.phase(args.phase)
    source = model_dir(task.name, cfg.previous, args.training_seed)
    bundle = load_bundle(root / source, device)
    files = TaskFiles(root, task.name, source, args.training_seed)
    seed = training_seed(derive_seed(cfg.generate.seed, args.phase), args.training_seed)
    print(f"{task.name} phase {args.phase} from {source}: {cfg.generate.tasks} tasks, torch threads "
          f"{torch.get_num_threads()}, discriminator rule {cfg.discriminate.rule}")  # fmt: skip
    for steps in args.steps:
        g = dataclasses.replace(cfg.generate, sampler="ddim", sampler_steps=steps)
        planner = Planner(bundle, make_sampler(g.sampler, g.sampler_steps), device)
        begin = time.perf_counter()
        generated, _ = family.generate(task, planner, files, g, params.alpha, seed, {"benchmark": True}, False)
        generate_s = time.perf_counter() - begin
        judgement = family.discriminate(task, generated, cfg.discriminate, args.phase, files, False)
        judged = judgement.report()
        details = "".join(f", {key} {value}" for key, value in judgement.details.items())  # the family's own counts
        tracked = judged["generated"] - judged["rejected_tracking"]
        print(f"DDIM {steps:3d} steps: {g.tasks / generate_s:6.1f} plans/s ({generate_s:5.1f} s); tracked "
              f"{tracked}, kept {judged['kept']} of {judged['generated']}{details}, kept mean return "
              f"{judged['return_mean_kept']:.1f}, tracking error {judged['tracking_error_mean']:.3f}",
              flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
