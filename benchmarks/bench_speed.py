"""Speed of the plain eager path against the pipeline's path, on the same inputs in one run (printed, never
asserted). Each pair is timed in alternating rounds and reported as the median round, so that a noisy neighbour
slows both sides alike.

* training: a step of the profile's batch with ``torch.optim.Adam`` as the trainers use it (plain) and with its
  fused kernel; with ``--compile`` also the network under ``torch.compile`` (its compile time printed);
* batched sampling: a batch of ``--batch`` plans with the generation sampler; with ``--compile`` the network under
  ``torch.compile`` (inductor, frozen weights) as well;
* a U-Maze decision at batch 1 with the profile's planner (also with coin guidance), the 16-step DDIM planner of
  earlier profiles and the full DDPM chain; evaluation throughput (protocol episodes in one batch);
* a locomotion decision (``quick-locomotion`` shapes: ``--episodes`` x ``--samples`` value-guided plans), as the
  profile plans (warm-started from the last plan) and from pure noise;
* generation throughput of an evolution phase (plans/s, the profile's generation settings).

It ends with machine-readable lines ``decision_ms_umaze_b1=``, ``speedup_train=``, ``speedup_sampling=``,
``locomotion_decision_s=`` (numbers only; the speedups are the pipeline's path over the plain eager one: 1.0 while
the pipeline runs the plain eager network, see the README's speed section).

    python benchmarks/bench_speed.py [--params params.yaml] [--rounds 5] [--compile] [--device cpu]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch
from speed_paths import alternate, locomotion_paths, maze_paths

from adaptdiffuser.diffusion.guidance import CoinObjective
from adaptdiffuser.stages.common import resolve_device


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
    parser.add_argument("--compile", action="store_true", help="also time torch.compile (minutes of compiling)")
    args = parser.parse_args()
    device = resolve_device(args.device)
    maze = maze_paths(args.params, args.task, device)
    task = maze.task
    print(f"{task.name}: {maze.source}; device {device}, torch threads {torch.get_num_threads()}, "
          f"model dim {task.model.dim} mults {task.model.dim_mults}, horizon {task.diffusion.horizon}")  # fmt: skip

    # training: plain Adam (the trainers'), its fused kernel, and optionally the compiled network
    model = maze.bundle.diffusion.to(device).train()
    x, cond = maze.training_batch(device)
    steps = {
        "plain": maze.training_step(device),
        "fused": maze.training_step(device, fused=True),
    }
    if args.compile:
        compiled = torch.compile(model.model)
        steps["compiled"], compile_s = _compiled_train_step(model, compiled, x, cond)
        print(f"torch.compile of the training step: {compile_s:.0f} s")
    train_ms = alternate(steps, args.rounds, device, calls=10)
    for name, ms in train_ms.items():
        print(f"training step, batch {x.shape[0]}, {name}: {ms:.1f} ms ({1000 / ms:.1f} steps/s)")
    speedup_train = 1.0  # the trainers use the plain path: neither alternative pays (README "Speed")

    # batched sampling with the generation sampler
    ema = maze.bundle.ema.to(device).eval()
    gen = maze.generation
    planner = maze.planner(gen.sampler, gen.sampler_steps, device)
    starts, goals = maze.start.repeat(args.batch, 0), maze.goal.repeat(args.batch, 0)
    seeds = list(range(args.batch))
    sampling = {"plain": lambda: planner.sample(starts, goals, seeds)}
    if args.compile:
        import torch._inductor.config as inductor_config

        inductor_config.freezing = True
        compiled_net = torch.compile(ema.model)
        with torch.no_grad():
            begin = time.perf_counter()
            compiled_net(torch.zeros(args.batch, ema.horizon, ema.transition_dim, device=device),
                         torch.zeros(args.batch, dtype=torch.long, device=device))  # fmt: skip
            print(f"torch.compile of the sampling network (batch {args.batch}): {time.perf_counter() - begin:.0f} s")

        def compiled_sample():
            with _network(ema, compiled_net):
                return planner.sample(starts, goals, seeds)

        sampling["compiled"] = compiled_sample
    sample_ms = alternate(sampling, args.rounds, device, calls=1)
    for name, ms in sample_ms.items():
        print(f"batched sampling, {args.batch} plans, {gen.sampler} {gen.sampler_steps}, {name}: {ms:.0f} ms")
    speedup_sampling = 1.0  # the pipeline samples with the plain eager network (see the README's speed section)

    # a U-Maze decision at batch 1
    pl = task.planner
    profile_planner = maze.planner(pl.sampler, pl.sampler_steps, device)
    coin = profile_planner.guidance(CoinObjective(maze.coin), maze.alpha)
    n_steps = task.diffusion.n_steps
    decisions = {
        f"profile {pl.sampler} {pl.sampler_steps}": (profile_planner, None),
        f"profile {pl.sampler} {pl.sampler_steps} with coin guidance": (profile_planner, coin),
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

    # generation throughput
    generate = maze.generate(device, args.generate_tasks)
    begin = time.perf_counter()
    generate()
    gen_s = time.perf_counter() - begin
    print(f"generation: {args.generate_tasks / gen_s:.1f} plans/s ({gen.sampler} {gen.sampler_steps}, batch "
          f"{gen.batch_size}, coin fraction {gen.coin_fraction})")  # fmt: skip

    print(f"decision_ms_umaze_b1={decision_ms[f'profile {pl.sampler} {pl.sampler_steps}']:.2f}")
    print(f"speedup_train={speedup_train:.3f}")
    print(f"speedup_sampling={speedup_sampling:.3f}")
    print(f"locomotion_decision_s={loco_s:.3f}")


def _compiled_train_step(model, compiled, x, cond) -> tuple[Callable[[], None], float]:
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-5)

    def step() -> None:
        with _network(model, compiled):
            model.loss(x, cond).backward()
        optimizer.step()
        optimizer.zero_grad()

    begin = time.perf_counter()
    step()
    return step, time.perf_counter() - begin


@contextmanager
def _network(diffusion, network) -> Iterator[None]:
    """Run ``diffusion`` with ``network`` (e.g. its compiled twin) in place of its own for the duration."""
    own = diffusion.model
    diffusion.model = network
    try:
        yield
    finally:
        diffusion.model = own


if __name__ == "__main__":
    main()
