"""Decision latency of the value-guided planner of a locomotion task (Diffuser's controller), printed (never
asserted): one decision = N start-conditioned plans for each of a batch of episodes, value-guided denoising,
then the first action of each episode's best plan. Uses the task's trained phase-0 model and value function
when `dvc repro` has made them, else untrained networks of the profile's shapes.

    python benchmarks/bench_value_planner.py [--params params.yaml] [--task hopper-medium] [--device cpu]
        [--episodes 1 10] [--samples 16 64] [--repeats 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from speed_paths import sync

from adaptdiffuser.checkpoint import load_bundle, make_bundle
from adaptdiffuser.config import load_params
from adaptdiffuser.data.normalizer import GaussianNormalizer
from adaptdiffuser.diffusion.guidance import ValueGuidance
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.layout import model_dir, value_dir
from adaptdiffuser.models.value_network import ValueNetwork
from adaptdiffuser.planning import Planner
from adaptdiffuser.stages.common import resolve_device
from adaptdiffuser.value_training import load_value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--task", default="hopper-medium")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--episodes", type=int, nargs="+", default=[1, 10])
    parser.add_argument("--samples", type=int, nargs="+", default=[16, 64])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    task = load_params(args.params).resolve(args.task)
    family = get_family(task.family)
    device = resolve_device(args.device)
    sim = family.make_simulator(task)
    if model_dir(task.name, 0, 0).exists() and value_dir(task.name, 0).exists():
        bundle = load_bundle(model_dir(task.name, 0, 0), device)
        value_net, _ = load_value(value_dir(task.name, 0), device)
        source = f"trained {model_dir(task.name, 0, 0)} and its value function"
    else:
        dim = sim.obs_dim + sim.act_dim
        bundle = make_bundle(task.model, task.diffusion, sim.obs_dim, sim.act_dim,
                             GaussianNormalizer(np.zeros(dim), np.ones(dim)), conditioning="start")  # fmt: skip
        vm = task.settings.value_model
        value_net = ValueNetwork(dim, task.diffusion.horizon, vm.dim, tuple(vm.dim_mults)).to(device).eval()
        source = "untrained networks of the profile's shapes"
    pl, g = task.planner, task.settings.guide
    print(f"{task.name}: device {device}, torch threads {torch.get_num_threads()}, {source}")
    print(f"horizon {task.diffusion.horizon}, {task.diffusion.n_steps} diffusion steps, sampler {pl.sampler}, "
          f"{g.n_guide_steps} guide steps (t >= {g.t_stopgrad}), model dim {task.model.dim}")  # fmt: skip
    planner = Planner(bundle, make_sampler(pl.sampler, pl.sampler_steps), device)
    guidance = ValueGuidance(value_net, g.scale, g.n_guide_steps, g.t_stopgrad, g.scale_grad_by_std)
    for episodes in args.episodes:
        sims = [family.make_simulator(task) for _ in range(episodes)]
        obs = np.stack([s.reset(np.random.default_rng(i)) for i, s in enumerate(sims)])
        for n in args.samples:
            controller = family.value_controller(planner, guidance, n, seed=0)
            controller.begin(sims, obs, list(range(episodes)))
            controller.act(sims, obs, 0)  # warm-up
            sync(device)
            start = time.perf_counter()
            for t in range(args.repeats):
                controller.act(sims, obs, t + 1)
            sync(device)
            ms = 1000 * (time.perf_counter() - start) / args.repeats
            minutes = ms * 1000 / 1000 / 60  # 1000 decisions per episode batch
            print(f"episodes {episodes:3d} x samples {n:3d}: {ms:8.1f} ms per decision "
                  f"({ms / episodes:7.1f} ms per episode-step; 1000 steps = {minutes:.1f} min)")  # fmt: skip


if __name__ == "__main__":
    main()
