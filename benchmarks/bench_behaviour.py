"""Which stable-baselines3 algorithm reaches the locomotion "medium" score fastest in wall-clock on this machine.

For each algorithm: train a behaviour policy on the env until the medium normalized score (or the step budget),
evaluating periodically; print the training steps per second, the steps and seconds to the target and the
scores reached (printed, never asserted), and write them as JSON.

    python benchmarks/bench_behaviour.py [--env Hopper-v5] [--algorithms td3 ppo sac] [--max-steps td3=80000 ...]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from adaptdiffuser.families.locomotion.behaviour import BehaviourSettings, train_behaviour

DEFAULT_STEPS = {"sac": 50_000, "td3": 60_000, "ppo": 400_000}
DEFAULT_EVAL_EVERY = {"sac": 5_000, "td3": 5_000, "ppo": 20_480}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--algorithms", nargs="+", default=["td3", "sac", "ppo"])
    parser.add_argument("--max-steps", nargs="*", default=[], help="algo=steps budgets")
    parser.add_argument("--medium-score", type=float, default=33.0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="bench_behaviour.json")
    args = parser.parse_args()
    budgets = DEFAULT_STEPS | {k: int(v) for k, v in (item.split("=") for item in args.max_steps)}
    results = {}
    for algo in args.algorithms:
        settings = BehaviourSettings(
            algorithm=algo, seed=args.seed, medium_score=args.medium_score, max_train_steps=budgets[algo],
            max_expert_steps=budgets[algo], eval_every=DEFAULT_EVAL_EVERY[algo], torch_threads=args.threads,
            medium_band=None,  # time to the first evaluation at the target (bench_behaviour_band.py: the band)
        )  # fmt: skip
        start, cpu_start, load_start = time.perf_counter(), time.process_time(), os.getloadavg()[0]
        with tempfile.TemporaryDirectory() as tmp:
            result = train_behaviour(args.env, Path(tmp), settings, progress=True)
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
        med = result.medium
        results[algo] = {
            "steps_per_s": result.learner.num_timesteps / wall,
            "reached": med["reached"],
            "steps": med["steps"],
            "wall_s": wall,
            "normalized_score": med["normalized_score"],
            "best_score": med["best_score"],
            "eval_every": settings.eval_every,
            "cpu_s": cpu,
            "load_avg_1min": [load_start, os.getloadavg()[0]],
            "curve": result.curve,
        }
        print(
            f"{algo}: {results[algo]['steps_per_s']:.0f} steps/s (incl. evaluation), "
            f"{'reached' if med['reached'] else 'did NOT reach'} {args.medium_score} after {med['steps']} steps "
            f"/ {wall:.0f} s; score {med['normalized_score']:.1f} (best {med['best_score']:.1f}); cpu {cpu:.0f} s, "
            f"load {load_start:.1f}->{os.getloadavg()[0]:.1f}",
            flush=True,
        )
        Path(args.out).write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
