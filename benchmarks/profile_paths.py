"""Where the time goes: the PyTorch profiler on the real paths, printed as shares of each path's operator time
(never asserted). Paths: a training step (the profile's batch), a batch-1 U-Maze decision with the profile's
planner, a batched DDIM plan (the generation batch), the same batch with coin guidance, and a value-guided
locomotion decision (quick-locomotion shapes, ``--episodes`` x ``--samples``).

    python benchmarks/profile_paths.py [--params params.yaml] [--repeats 5] [--episodes 10] [--samples 64]
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from collections.abc import Callable

import torch
from speed_paths import locomotion_paths, maze_paths
from torch.profiler import ProfilerActivity, profile

from adaptdiffuser.stages.common import resolve_device

#: operator name fragments -> category, first match wins
CATEGORIES = [
    ("convolution_backward", "conv backward"),
    ("conv", "conv forward"),
    ("mish_backward", "Mish backward"),
    ("mish", "Mish"),
    ("group_norm_backward", "GroupNorm backward"),
    ("group_norm", "GroupNorm"),
    ("adam", "Adam"),
    ("mm", "linear (time embedding, value head)"),
    ("randn", "noise"),
    ("normal", "noise"),
]


def category(name: str) -> str:
    lowered = name.lower()
    for fragment, label in CATEGORIES:
        if fragment in lowered:
            return label
    return "other operators (add, mul, cat, copy, indexing, ...)"


def breakdown(fn: Callable[[], object], repeats: int) -> tuple[float, dict[str, float]]:
    """Wall milliseconds per call and the share of self CPU time per category (plus the wall time outside
    operators: Python, dispatch, numpy and the simulator)."""
    fn()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        begin = time.perf_counter()
        for _ in range(repeats):
            fn()
        wall = (time.perf_counter() - begin) / repeats * 1000
    totals: dict[str, float] = defaultdict(float)
    for event in prof.key_averages():
        if event.key.startswith(("aten::", "Optimizer")) or "adam" in event.key.lower():
            totals[category(event.key)] += event.self_cpu_time_total / 1000 / repeats
    # self times of parallel regions count CPU time, so they can exceed wall time on 2 threads: report shares
    operators = sum(totals.values())
    return wall, {name: value / operators for name, value in sorted(totals.items(), key=lambda kv: -kv[1])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--task", default=None)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--samples", type=int, default=64)
    args = parser.parse_args()
    device = resolve_device(args.device)
    maze = maze_paths(args.params, args.task, device)
    task, gen = maze.task, maze.generation
    train_step = maze.training_step(device)

    pl = task.planner
    decision = maze.planner(pl.sampler, pl.sampler_steps, device)
    batched = maze.planner(gen.sampler, gen.sampler_steps, device)
    n = gen.batch_size
    starts, goals, seeds = maze.start.repeat(n, 0), maze.goal.repeat(n, 0), list(range(n))
    coin = maze.coin_guidance(batched, n)
    loco = locomotion_paths(device, args.episodes, args.samples)
    decide = loco.decision()
    lp = loco.task.planner
    paths = {
        f"training step (batch {task.pretrain.batch_size})": train_step,
        f"U-Maze decision, batch 1 ({pl.sampler} {pl.sampler_steps})": lambda: decision.plan(
            maze.start, maze.goal, [0]
        ),
        f"batched plan ({n} plans, {gen.sampler} {gen.sampler_steps})": lambda: batched.sample(starts, goals, seeds),
        f"batched plan with coin guidance ({n} plans)": lambda: batched.sample(starts, goals, seeds, coin),
        f"locomotion decision ({args.episodes} x {args.samples}, {lp.sampler} {lp.sampler_steps}, value-guided)": (
            lambda: decide(1)
        ),
    }
    print(f"device {device}, torch threads {torch.get_num_threads()}; shares of operator time per path")
    for name, fn in paths.items():
        repeats = 1 if "locomotion" in name else args.repeats
        wall, shares = breakdown(fn, repeats)
        print(f"\n{name}: {wall:.1f} ms per call (under the profiler)")
        for label, share in shares.items():
            if share >= 0.01:
                print(f"  {100 * share:5.1f} %  {label}")
    guidance = loco.controller.guidance
    guidance.scale = 0.0  # the same decision with the value gradients skipped (the value still ranks the plans)
    wall, _ = breakdown(lambda: decide(1), 1)
    print(f"\nlocomotion decision without the value-gradient steps: {wall:.1f} ms per call (under the profiler)")


if __name__ == "__main__":
    main()
