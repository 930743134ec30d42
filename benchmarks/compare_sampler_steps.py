"""Score and decision latency of a trained planner at several sampler settings, side by side on the same episodes
(printed, never asserted): fewer network calls per decision against what they cost in score.

For each DDIM step count (and the full DDPM chain with ``--ddpm``), the task's phase-k model of one training seed is
evaluated under the task's protocol on ``--episodes`` episodes from ``--seed`` (a validation seed by default, not
the evaluation seed ``evaluate.seed``: choose on it, then confirm once with ``--seed`` set to the evaluation seed),
with the gain over the profile's own sampler paired per episode, and the latency of one decision at batch 1.

    python benchmarks/compare_sampler_steps.py WORKSPACE [--task maze2d-umaze] [--steps 4 6 8 10 12 16]
        [--seed 7] [--episodes 50] [--phase 0] [--training-seed 0]

WORKSPACE is a pipeline folder after `dvc repro` (its params.yaml, models/ and metrics/tasks/<task>/reference.json).
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
    parser.add_argument("--task", default=None, help="a task of params (default: the evolved task)")
    parser.add_argument("--steps", type=int, nargs="+", default=[4, 6, 8, 10, 12, 16])
    parser.add_argument("--ddpm", action="store_true", help="also the full DDPM chain")
    parser.add_argument("--seed", type=int, default=7, help="episode seed (default 7: validation, not evaluation)")
    parser.add_argument("--episodes", type=int, default=None, help="default: the task's evaluate.episodes")
    parser.add_argument("--phase", type=int, default=0)
    parser.add_argument("--training-seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=10, help="decisions timed at batch 1")
    parser.add_argument("--device", default="auto")
    args = parser.parse_args()
    root = args.workspace.resolve()
    raw = yaml.safe_load((root / "params.yaml").read_text())
    name = args.task or raw.get("evolve") or raw["tasks"][0]
    raw = set_dotted(raw, f"task.{name}.evaluate.seed", args.seed)
    if args.episodes is not None:
        raw = set_dotted(raw, f"task.{name}.evaluate.episodes", args.episodes)
    task = params_from_dict(raw).resolve(name)
    family = get_family(task.family)
    device = resolve_device(args.device)
    model = model_dir(task.name, args.phase, args.training_seed)
    bundle = load_bundle(root / model, device)
    ref = read_json(root / reference_path(task.name), f"reference scores of {task.name}")
    files = TaskFiles(root, task.name, model, args.training_seed)
    ev = task.evaluate
    print(f"{task.name} phase {args.phase} (training seed {args.training_seed}), {ev.episodes} episodes from seed "
          f"{args.seed}, torch threads {torch.get_num_threads()}, profile sampler {task.planner.sampler} "
          f"{task.planner.sampler_steps}")  # fmt: skip

    settings = [("ddim", n) for n in args.steps] + ([("ddpm", task.diffusion.n_steps)] if args.ddpm else [])
    profile_setting = (task.planner.sampler, task.planner.sampler_steps)
    if profile_setting not in settings:
        settings.append(profile_setting)
    scores = {}
    for kind, steps in settings:
        planner = Planner(bundle, make_sampler(kind, steps), device)
        start = time.perf_counter()
        result = run_episodes(
            lambda: family.make_simulator(task),
            family.controller(task, planner, files, device),
            ev.episodes,
            ev.seed,
            ev.batch_size,
            progress=False,
        )
        elapsed = time.perf_counter() - start
        scores[(kind, steps)] = normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"])
        decision_ms = _decision_ms(planner, family.make_simulator(task), args.repeats, device)
        print(f"{kind} {steps:3d} steps: score {scores[(kind, steps)].mean():6.1f} +- "
              f"{standard_error(scores[(kind, steps)]):4.1f}, decision at batch 1 {decision_ms:6.1f} ms, "
              f"evaluation {elapsed:5.1f} s", flush=True)  # fmt: skip
    print(f"gain over the profile's {profile_setting[0]} {profile_setting[1]}, paired per episode:")
    for setting, values in scores.items():
        if setting != profile_setting:
            gain = paired_gain(values, scores[profile_setting])
            print(f"  {setting[0]} {setting[1]:3d} steps: {gain['gain_mean']:+6.1f} +- {gain['gain_stderr']:4.1f}")


def _decision_ms(planner: Planner, sim, repeats: int, device: torch.device) -> float:
    """Milliseconds of one batch-1 plan from a protocol start (to the simulator's goal for goal-conditioned models)."""
    start = sim.reset(np.random.default_rng(0))[None]
    goal = sim.goal_state()[None] if planner.conditioning == "start_goal" else None
    planner.plan(start, goal, [0])
    if device.type == "cuda":
        torch.cuda.synchronize()
    begin = time.perf_counter()
    for r in range(repeats):
        planner.plan(start, goal, [r + 1])
    if device.type == "cuda":
        torch.cuda.synchronize()
    return 1000 * (time.perf_counter() - begin) / repeats


if __name__ == "__main__":
    main()
