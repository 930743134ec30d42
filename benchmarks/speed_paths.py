"""The real paths the speed benchmarks time and profile, and their timing helper (not a benchmark itself).

A Maze2D task's planner (the trained phase-0 model of the workspace when `dvc repro` has made it, else an
untrained model of the profile's shape) and a locomotion task's value-guided controller (networks of the shapes of
``profiles/quick-locomotion.yaml`` unless the params name a locomotion task).
"""

from __future__ import annotations

import copy
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from adaptdiffuser.checkpoint import ModelBundle, load_bundle, make_bundle
from adaptdiffuser.config import GenerateParams, TaskParams, apply_profile, load_params
from adaptdiffuser.contract import Controller, TaskFiles
from adaptdiffuser.data.normalizer import GaussianNormalizer, MinMaxNormalizer
from adaptdiffuser.diffusion.guidance import Guidance, Objective, ValueGuidance
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.evaluation import run_episodes
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.layout import model_dir
from adaptdiffuser.models.compiled import compile_network
from adaptdiffuser.models.value_network import ValueNetwork
from adaptdiffuser.planning import Planner

PROFILES = Path(__file__).resolve().parents[1] / "profiles"


class PointPull(Objective):
    """``J = -sum_t ||xy_t - point||``: minus how far each plan's positions pass from its point (``points``:
    ``[batch, 2]``), the arithmetic of the Maze2D coin guidance, so a guided path costs here what it costs there."""

    def __init__(self, points: torch.Tensor, eps: float = 1e-6) -> None:
        self.points = points
        self.eps = eps

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        delta = states[..., :2] - self.points.to(states)[:, None, :]
        return -torch.sqrt((delta**2).sum(-1) + self.eps**2).sum(-1)


@dataclass
class MazePaths:
    """A Maze2D task with its planner's bundle, its phase-1 generation settings and one protocol start/goal."""

    task: TaskParams
    generation: GenerateParams
    bundle: ModelBundle
    source: str
    start: np.ndarray
    goal: np.ndarray
    coin: torch.Tensor
    alpha: float
    compile_sampling: bool  # params compile.sampling: whether the profile's planner runs compiled

    def planner(self, sampler: str, steps: int, device: torch.device, compiled: bool = False) -> Planner:
        """The bundle's planner; ``compiled``: a copy of its EMA network under ``torch.compile`` (the fast path)."""
        bundle = replace(self.bundle, ema=copy.deepcopy(self.bundle.ema)) if compiled else self.bundle
        return Planner(bundle, make_sampler(sampler, steps), device, compiled=compiled)

    def coin_guidance(self, planner: Planner, n: int) -> Guidance:
        """Guidance of ``n`` plans toward the coin at scale ``alpha`` (the unseen task's guidance, as generation
        uses it)."""
        return planner.guidance(PointPull(self.coin.repeat(n, 1)), self.alpha)

    def training_batch(
        self, device: torch.device, size: int | None = None
    ) -> tuple[torch.Tensor, dict[int, torch.Tensor]]:
        """A fixed batch of ``size`` trajectories (default: the profile's batch size) and its start/goal inpainting
        conditions."""
        model = self.bundle.diffusion
        gen = torch.Generator().manual_seed(0)
        size = size or self.task.pretrain.batch_size
        x = torch.rand(size, model.horizon, model.transition_dim, generator=gen) * 2 - 1
        x = x.to(device)
        return x, {0: x[:, 0, model.act_dim :], model.horizon - 1: x[:, -1, model.act_dim :]}

    def training_step(self, device: torch.device, compiled: bool = False) -> Callable[[], None]:
        """One training step of the planner's model on :meth:`training_batch` (Adam, as the trainers use it);
        ``compiled``: a copy of the model with its network under ``torch.compile``."""
        model = self.bundle.diffusion.to(device).train()
        if compiled:
            model = copy.deepcopy(model)
            compile_network(model.model, device, "compile.training")
        optimizer = torch.optim.Adam(model.parameters(), lr=1e-5)
        x, cond = self.training_batch(device)

        def step() -> None:
            model.loss(x, cond).backward()
            optimizer.step()
            optimizer.zero_grad()

        return step

    def files(self) -> TaskFiles:
        return TaskFiles(Path("."), self.task.name, model_dir(self.task.name, 0, 0), 0)

    def generate(self, device: torch.device, tasks: int, compiled: bool = False) -> Callable[[], object]:
        """One call of the family's generation (``tasks`` plans of the profile's generation settings)."""
        g = replace(self.generation, tasks=tasks)
        planner = self.planner(g.sampler, g.sampler_steps, device, compiled)
        family = get_family(self.task.family)
        return lambda: family.generate(self.task, planner, self.files(), g, self.alpha, 0, {}, False)

    def evaluate(self, device: torch.device, episodes: int) -> Callable[[], object]:
        """``episodes`` protocol episodes in one batch with the profile's planner and the family's controller."""
        pl = self.task.planner
        planner = self.planner(pl.sampler, pl.sampler_steps, device, self.compile_sampling)
        family = get_family(self.task.family)
        controller = family.controller(self.task, planner, self.files(), device)
        make_env = lambda: family.make_simulator(self.task)  # noqa: E731
        return lambda: run_episodes(make_env, controller, episodes, self.task.evaluate.seed, episodes, progress=False)


def maze_paths(params_path: str, task_name: str | None, device: torch.device) -> MazePaths:
    """The Maze2D task of ``params_path`` (default: the evolved task) and its planner's bundle."""
    params = load_params(params_path)
    task = params.resolve(task_name or params.evolve or params.tasks[0])
    env = get_family(task.family).make_simulator(task)
    path = model_dir(task.name, 0, 0)
    if path.exists():
        bundle, source = load_bundle(path, device), f"trained {path}"
    else:
        dim = env.obs_dim + env.act_dim
        normalizer = MinMaxNormalizer(-np.ones(dim) * 5, np.ones(dim) * 5)
        bundle = make_bundle(task.model, task.diffusion, env.obs_dim, env.act_dim, normalizer)
        source = "an untrained model of the profile's shape"
    # the coin: the position of another start of the protocol (a point inside the maze, through the contract only)
    coin = torch.as_tensor(env.reset(np.random.default_rng(1))[None, :2], dtype=torch.float32, device=device)
    start = env.reset(np.random.default_rng(0))[None]
    generation = params.phase(1).generate
    goal, alpha = env.goal_state()[None], max(params.alpha, 1.0)
    return MazePaths(task, generation, bundle, source, start, goal, coin, alpha, params.compile.sampling)


@dataclass
class LocomotionPaths:
    """A locomotion task's value-guided controller on a batch of episodes."""

    task: TaskParams
    controller: Controller
    sims: list
    obs: np.ndarray

    def decision(self) -> Callable[[int], np.ndarray]:
        return lambda t: self.controller.act(self.sims, self.obs, t)


def locomotion_paths(
    device: torch.device,
    episodes: int,
    samples: int,
    sampler: str | None = None,
    steps: int | None = None,
    warm_start: bool = True,
) -> LocomotionPaths:
    """Untrained networks of ``quick-locomotion``'s hopper-medium shapes and its planner (or ``sampler``/``steps``),
    ``episodes`` simulators reset from seeds 0.., ``samples`` plans per episode per decision; decisions after the
    first warm-start as the profile says (``guide.warm_start_step``), or from pure noise without ``warm_start``."""
    with tempfile.TemporaryDirectory() as tmp:
        params_path = Path(tmp) / "params.yaml"
        params_path.write_text((PROFILES.parent / "params.yaml").read_text())
        apply_profile("quick-locomotion", PROFILES, params_path)
        params = load_params(params_path)
    task = params.resolve("hopper-medium")
    family = get_family(task.family)
    sim = family.make_simulator(task)
    dim = sim.obs_dim + sim.act_dim
    normalizer = GaussianNormalizer(np.zeros(dim), np.ones(dim))
    bundle = make_bundle(task.model, task.diffusion, sim.obs_dim, sim.act_dim, normalizer, conditioning="start")
    vm = task.settings.value_model
    value_net = ValueNetwork(dim, task.diffusion.horizon, vm.dim, tuple(vm.dim_mults)).to(device).eval()
    g = task.settings.guide
    sampler_ = make_sampler(sampler or task.planner.sampler, steps or task.planner.sampler_steps)
    planner = Planner(bundle, sampler_, device)
    guidance = ValueGuidance(value_net, g.scale, g.n_guide_steps, g.t_stopgrad, g.scale_grad_by_std)
    warm = g.warm_start_step if warm_start else None
    controller = family.value_controller(planner, guidance, samples, seed=0, warm_start_step=warm)
    sims = [family.make_simulator(task) for _ in range(episodes)]
    obs = np.stack([s.reset(np.random.default_rng(i)) for i, s in enumerate(sims)])
    controller.begin(sims, obs, list(range(episodes)))
    return LocomotionPaths(task, controller, sims, obs)


def alternate(
    functions: dict[str, Callable[[], object]], rounds: int, device: torch.device, calls: int
) -> dict[str, float]:
    """Median milliseconds per call of each function: ``rounds`` rounds, each timing ``calls`` calls of every
    function in turn, after one warm-up call each."""
    times: dict[str, list[float]] = {name: [] for name in functions}
    for f in functions.values():
        f()
    for _ in range(rounds):
        for name, f in functions.items():
            sync(device)
            begin = time.perf_counter()
            for _ in range(calls):
                f()
            sync(device)
            times[name].append(1000 * (time.perf_counter() - begin) / calls)
    return {name: statistics.median(values) for name, values in times.items()}


def sync(device: torch.device) -> None:
    """Wait for the device's queued work (CUDA); nothing on the CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize()
