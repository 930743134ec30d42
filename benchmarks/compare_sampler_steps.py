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
    parser.add_argument("--steps", type=int, nargs="+", default=[4, 6, 8, 10, 12, 16])
    parser.add_argument("--ddpm", action="store_true", help="also the full DDPM chain")
    parser.add_argument("--repeats", type=int, default=10, help="decisions timed at batch 1")
    args = parser.parse_args()
    ws = load_trained(args)
    task, device, bundle = ws.task(), ws.device, ws.bundle
    family = get_family(task.family)
    ref, files, ev = ws.reference(), ws.files(), task.evaluate
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
