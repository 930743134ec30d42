"""Speed of the plain eager path against the fast path (the network under ``torch.compile``, params ``compile``),
on the same inputs in one run (printed, never asserted). Each pair is timed in alternating rounds and reported as
the median round, so that a noisy neighbour slows both sides alike. The first call of each compiled path is timed
apart (compiling: tens of seconds, a few from inductor's on-disk cache).

* training: a step of the profile's batch with ``torch.optim.Adam`` as the trainers use it, eager and compiled
  (``compile.training``);
* batched sampling: a batch of ``--batch`` plans with the generation sampler, eager and compiled
  (``compile.sampling``);
* a U-Maze decision at batch 1 with the profile's planner (also with coin guidance), the 16-step DDIM planner of
  earlier profiles and the full DDPM chain; evaluation throughput (protocol episodes in one batch);
* a locomotion decision (``quick-locomotion`` shapes: ``--episodes`` x ``--samples`` value-guided plans), as the
  profile plans (warm-started from the last plan) and from pure noise;
* generation throughput of an evolution phase (plans/s, the profile's generation settings), eager and compiled.

It ends with machine-readable lines ``decision_ms_umaze_b1=``, ``speedup_train=``, ``speedup_sampling=``,
``locomotion_decision_s=``, ``speedup_generation=`` (numbers only; speedups are eager time over compiled time).

    python benchmarks/bench_speed.py [--params params.yaml] [--rounds 5] [--device cpu]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import torch
from speed_paths import alternate, locomotion_paths, maze_paths

from adaptdiffuser.stages.common import resolve_device

PATHS = ("plain", "compiled")  # the eager network and the fast path, timed side by side


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--task", default=None, help="a maze2d task of params (default: the evolved task)")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--batch", type=int, default=256, help="plans per batch for the sampling figure")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--generate-tasks", type=int, default=512)
    parser.add_argument("--eval-episodes", type=int, default=50)
    args = parser.parse_args()
    device = resolve_device(args.device)
    maze = maze_paths(args.params, args.task, device)
    task = maze.task
    print(f"{task.name}: {maze.source}; device {device}, torch threads {torch.get_num_threads()}, "
          f"model dim {task.model.dim} mults {task.model.dim_mults}, horizon {task.diffusion.horizon}")  # fmt: skip

    # training: the trainers' step, eager and compiled
    batch = task.pretrain.batch_size
    steps = {name: maze.training_step(device, compiled=name == "compiled") for name in PATHS}
    print(f"compiling the training step: {_first_call_s(steps['compiled']):.0f} s")
    train_ms = alternate(steps, args.rounds, device, calls=10)
    for name, ms in train_ms.items():
        print(f"training step, batch {batch}, {name}: {ms:.1f} ms ({1000 / ms:.1f} steps/s)")
    speedup_train = train_ms["plain"] / train_ms["compiled"]

    # batched sampling with the generation sampler, eager and compiled
    gen = maze.generation
    starts, goals = maze.start.repeat(args.batch, 0), maze.goal.repeat(args.batch, 0)
    seeds = list(range(args.batch))
    planners = {name: maze.planner(gen.sampler, gen.sampler_steps, device, name == "compiled") for name in PATHS}
    sampling = {name: (lambda p=p: p.sample(starts, goals, seeds)) for name, p in planners.items()}
    print(f"compiling the sampling network (batch {args.batch}): {_first_call_s(sampling['compiled']):.0f} s")
    sample_ms = alternate(sampling, args.rounds, device, calls=1)
    for name, ms in sample_ms.items():
        print(f"batched sampling, {args.batch} plans, {gen.sampler} {gen.sampler_steps}, {name}: {ms:.0f} ms")
    speedup_sampling = sample_ms["plain"] / sample_ms["compiled"]

    # a U-Maze decision at batch 1 (the profile's planner, eager or compiled as compile.sampling says, and the other)
    pl = task.planner
    profile_planner = maze.planner(pl.sampler, pl.sampler_steps, device, maze.compile_sampling)
    coin = maze.coin_guidance(profile_planner, 1)
    other = maze.planner(pl.sampler, pl.sampler_steps, device, not maze.compile_sampling)
    n_steps = task.diffusion.n_steps
    decisions = {
        f"profile {pl.sampler} {pl.sampler_steps}": (profile_planner, None),
        f"profile {pl.sampler} {pl.sampler_steps} with coin guidance": (profile_planner, coin),
        f"{pl.sampler} {pl.sampler_steps}, {'eager' if maze.compile_sampling else 'compiled'}": (other, None),
        "ddim 16 (earlier profiles)": (maze.planner("ddim", 16, device), None),
        f"ddpm {n_steps} (the full chain)": (maze.planner("ddpm", n_steps, device), None),
    }
    decision_ms = alternate(
        {name: (lambda p=p, g=g: p.plan(maze.start, maze.goal, [0], guidance=g)) for name, (p, g) in decisions.items()},
        args.rounds,
        device,
        calls=10,
    )
    for name, ms in decision_ms.items():
        print(f"U-Maze decision at batch 1, {name}: {ms:.1f} ms")

    # evaluation throughput: protocol episodes in one batch, the profile's planner and controller
    evaluate = maze.evaluate(device, args.eval_episodes)
    begin = time.perf_counter()
    evaluate()
    eval_s = time.perf_counter() - begin
    print(f"evaluation: {args.eval_episodes / eval_s:.1f} episodes/s ({args.eval_episodes} episodes in one batch)")

    # a locomotion decision
    loco = locomotion_paths(device, args.episodes, args.samples)
    decide = loco.decision()
    decide(0)
    loco_s = alternate({"profile": lambda: decide(1)}, args.rounds, device, calls=1)["profile"] / 1000
    lp, guide = loco.task.planner, loco.task.settings.guide
    start = "pure noise" if guide.warm_start_step is None else f"the last plan noised to step {guide.warm_start_step}"
    print(f"locomotion decision, {args.episodes} episodes x {args.samples} samples, {lp.sampler} {lp.sampler_steps}, "
          f"{guide.n_guide_steps} value-gradient steps, from {start}: {loco_s:.2f} s")  # fmt: skip
    cold = locomotion_paths(device, args.episodes, args.samples, warm_start=False).decision()
    cold(0)
    cold_s = alternate({"cold": lambda: cold(1)}, args.rounds, device, calls=1)["cold"] / 1000
    print(f"the same from pure noise every decision (Diffuser): {cold_s:.2f} s")

    # generation throughput, eager and compiled (each a fresh planner: the compiled one's first batches compile)
    plans_s = {}
    for name in PATHS:
        generate = maze.generate(device, args.generate_tasks, compiled=name == "compiled")
        begin = time.perf_counter()
        generate()
        plans_s[name] = args.generate_tasks / (time.perf_counter() - begin)
        coins = maze.task.settings.evolution.coin_fraction
        print(f"generation, {name}: {plans_s[name]:.1f} plans/s ({gen.sampler} {gen.sampler_steps}, batch "
              f"{gen.batch_size}, coin fraction {coins}; compiling included)")  # fmt: skip

    print(f"decision_ms_umaze_b1={decision_ms[f'profile {pl.sampler} {pl.sampler_steps}']:.2f}")
    print(f"speedup_train={speedup_train:.3f}")
    print(f"speedup_sampling={speedup_sampling:.3f}")
    print(f"locomotion_decision_s={loco_s:.3f}")
    print(f"speedup_generation={plans_s['compiled'] / plans_s['plain']:.3f}")


def _first_call_s(fn: Callable[[], object]) -> float:
    """Seconds of one call of ``fn`` (a compiled path's first call: compiling)."""
    begin = time.perf_counter()
    fn()
    return time.perf_counter() - begin


if __name__ == "__main__":
    main()
