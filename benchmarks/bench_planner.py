"""Speed figures of a Maze2D task of the current params.yaml profile, printed (never asserted).

Prints: training steps per second, plan latency per decision (batch 1) for the full DDPM chain and the strided
DDIM sampler, evaluation episodes per second (batched planning + simulation), and the profile's score as
recorded by the last `dvc repro` in metrics/summary.json.

    python benchmarks/bench_planner.py [--params params.yaml] [--task maze2d-umaze] [--device cpu] [--repeats 10]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from adaptdiffuser.checkpoint import load_bundle, make_bundle
from adaptdiffuser.config import load_params
from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.diffusion.guidance import CoinObjective
from adaptdiffuser.diffusion.samplers import DDIMSampler, DDPMSampler
from adaptdiffuser.evaluation import run_episodes
from adaptdiffuser.families.maze2d.execution import PlannerController
from adaptdiffuser.families.registry import get_family
from adaptdiffuser.planning import Planner
from adaptdiffuser.stages.common import model_dir, resolve_device


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--task", default=None, help="a maze2d task of params (default: the evolved task)")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--train-steps", type=int, default=30)
    parser.add_argument("--episodes", type=int, default=50)
    args = parser.parse_args()
    all_params = load_params(args.params)
    params = all_params.resolve(args.task or all_params.evolve or all_params.tasks[0])
    family = get_family(params.family)

    def make_env():
        return family.make_simulator(params)

    device = resolve_device(args.device)
    env = make_env()
    model_path = model_dir(params.name, 0, 0)
    if model_path.exists():
        bundle = load_bundle(model_path, device)
        source = f"trained {model_path}"
    else:
        dim = env.obs_dim + env.act_dim
        normalizer = MinMaxNormalizer(-np.ones(dim) * 5, np.ones(dim) * 5)
        bundle = make_bundle(params.model, params.diffusion, env.obs_dim, env.act_dim, normalizer)
        source = "untrained model of the profile's shape"
    print(f"device {device}, torch threads {torch.get_num_threads()}, {source}")
    print(
        f"model dim {params.model.dim} mults {params.model.dim_mults}, horizon {params.diffusion.horizon}, "
        f"{sum(p.numel() for p in bundle.diffusion.parameters()) / 1e6:.2f} M parameters"
    )

    # training throughput
    model = bundle.diffusion.to(device).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=params.pretrain.lr)
    x = torch.rand(params.pretrain.batch_size, params.diffusion.horizon, model.transition_dim, device=device) * 2 - 1
    cond = {0: x[:, 0, model.act_dim :], model.horizon - 1: x[:, -1, model.act_dim :]}
    for i in range(args.train_steps + 5):
        if i == 5:
            _sync(device)
            start = time.perf_counter()
        loss = model.loss(x, cond)
        loss.backward()
        optimizer.step()
        optimizer.zero_grad()
    _sync(device)
    rate = args.train_steps / (time.perf_counter() - start)
    print(f"training: {rate:.1f} steps/s (batch {params.pretrain.batch_size})")

    # plan latency per decision, batch 1
    start_state = env.reset(np.random.default_rng(0))[None]
    goal = env.goal_state()[None]
    for name, sampler in [
        (f"DDPM chain ({params.diffusion.n_steps} steps)", DDPMSampler()),
        (f"DDIM strided ({params.planner.sampler_steps} steps)", DDIMSampler(params.planner.sampler_steps)),
    ]:
        planner = Planner(bundle, sampler, device)
        planner.plan(start_state, goal, [0])
        _sync(device)
        start = time.perf_counter()
        for r in range(args.repeats):
            planner.plan(start_state, goal, [r])
        _sync(device)
        print(f"plan latency, {name}: {1000 * (time.perf_counter() - start) / args.repeats:.1f} ms per decision")

    # the same DDIM plan with coin guidance (one extra backward pass through the normalizer and J per step)
    planner = Planner(bundle, DDIMSampler(params.planner.sampler_steps), device)
    coin = torch.as_tensor(env.cell_to_xy(env.layout.free_cells[0])[None], dtype=torch.float32, device=device)
    guidance = planner.guidance(CoinObjective(coin), max(all_params.alpha, 1.0))
    planner.plan(start_state, goal, [0], guidance=guidance)
    _sync(device)
    start = time.perf_counter()
    for r in range(args.repeats):
        planner.plan(start_state, goal, [r], guidance=guidance)
    _sync(device)
    elapsed_ms = 1000 * (time.perf_counter() - start) / args.repeats
    print(f"plan latency, DDIM strided with coin guidance: {elapsed_ms:.1f} ms per decision")

    # evaluation throughput with the profile's planner
    pl = params.planner
    sampler = DDIMSampler(pl.sampler_steps) if pl.sampler == "ddim" else DDPMSampler()
    controller = PlannerController(Planner(bundle, sampler, device), seed=0, replan_every=pl.replan_every)
    start = time.perf_counter()
    run_episodes(make_env, controller, args.episodes, 0, args.episodes, progress=False)
    elapsed = time.perf_counter() - start
    print(
        f"evaluation: {args.episodes / elapsed:.2f} episodes/s "
        f"({args.episodes} episodes of {env.episode_steps} steps, one batch, {pl.sampler}, replan {pl.replan_every})"
    )

    summary = Path("metrics/summary.json")
    if summary.exists():
        for phase, entry in json.loads(summary.read_text()).get(params.name, {}).items():
            if not phase.startswith("phase_"):
                continue
            print(
                f"score (metrics/summary.json, {phase}): {entry['score_mean']:.1f} +- {entry['score_stderr']:.1f} "
                f"over {entry['n_episodes']} episodes, success rate {entry['success_rate']:.2f}"
            )
    else:
        print("score: run `dvc repro` first (metrics/summary.json not found)")


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


if __name__ == "__main__":
    main()
