"""Batch-independent plan sampling: every row draws its noise from its own seed, so a row's sample (and an
evaluation episode's plans, actions and return) is the same alone, in any batch and at any position in it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import maze_sim

from adaptdiffuser.checkpoint import ModelBundle, make_bundle
from adaptdiffuser.config import DiffusionParams, ModelParams, Params, apply_profile, params_from_dict
from adaptdiffuser.contract import EpisodeBatchResult, TaskFiles
from adaptdiffuser.data.normalizer import GaussianNormalizer, MinMaxNormalizer
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.diffusion.gaussian import GaussianDiffusion
from adaptdiffuser.diffusion.guidance import Guidance, GuidanceBase, ValueGuidance
from adaptdiffuser.diffusion.noise import RowNoise, stream_words
from adaptdiffuser.diffusion.samplers import DDIMSampler, DDPMSampler, Sampler
from adaptdiffuser.evaluation import run_episodes
from adaptdiffuser.families.maze2d.execution import PlannerController
from adaptdiffuser.families.maze2d.generation import generate_plans
from adaptdiffuser.families.maze2d.gold_coin import CoinObjective
from adaptdiffuser.families.maze2d.tasks import add_coins, sample_navigation_tasks
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.models.value_network import ValueNetwork
from adaptdiffuser.planning import Planner
from adaptdiffuser.value_training import save_value

CPU = torch.device("cpu")
PROFILES = Path(__file__).resolve().parents[1] / "profiles"
OBS, ACT, H = 4, 2, 16
SEEDS = [derive_seed(7, i) for i in range(4)]
TINY = ModelParams(dim=8, dim_mults=[1, 2])
# an epsilon-predicting model follows its input even untrained, so guidance visibly moves the samples
DIFFUSION = DiffusionParams(horizon=H, n_steps=8, predict_epsilon=True)


def test_row_noise_rows_are_their_own_counter_based_streams() -> None:
    noise = RowNoise(SEEDS)
    first, second = noise.randn((3, 5)), noise.randn((2,))
    assert len(noise) == 4 and first.shape == (4, 3, 5) and second.shape == (4, 2)
    # a row's draws do not depend on the other rows nor on its position
    alone = RowNoise([SEEDS[2]])
    reordered = RowNoise([SEEDS[3], SEEDS[2], SEEDS[0]])
    assert torch.equal(alone.randn((3, 5))[0], first[2]) and torch.equal(reordered.randn((3, 5))[1], first[2])
    # the d-th draw is the d-th draw, whatever the rows: the second draw follows from the seed and the index alone
    assert torch.equal(alone.randn((2,))[0], second[2]) and torch.equal(reordered.randn((2,))[1], second[2])
    assert not torch.equal(first[0], first[1])
    assert not torch.equal(first[:, 0, :2], second)  # the next draw is new noise, not the first one again
    assert torch.equal(RowNoise(np.array(SEEDS, dtype=np.uint32)).randn((3, 5)), first)
    # the same numbers in every precision, up to the precision's rounding
    double = RowNoise(SEEDS, dtype=torch.float64).randn((3, 5))
    torch.testing.assert_close(double.float(), first, rtol=1e-5, atol=1e-5)


def test_row_noise_is_standard_normal_and_uncorrelated() -> None:
    """Many rows of neighbouring seeds, two draws: moments of N(0, 1), tails, and no correlation between
    neighbouring rows, neighbouring elements or successive draws."""
    noise = RowNoise(range(2000), dtype=torch.float64)
    a, b = noise.randn((500,)), noise.randn((500,))
    values = a.flatten()
    n = values.numel()  # 1e6: the mean's standard error is 1e-3
    assert abs(float(values.mean())) < 5e-3 and abs(float(values.std()) - 1.0) < 5e-3
    assert abs(float((values**3).mean())) < 2e-2 and abs(float((values**4).mean()) - 3.0) < 5e-2
    assert abs(float((values.abs() > 3.0).double().mean()) - 0.0027) < 5 * (0.0027 / n) ** 0.5
    for x, y in [(a[:-1], a[1:]), (a[:, :-1], a[:, 1:]), (a, b)]:
        assert abs(float((x * y).mean())) < 5e-3


def test_row_noise_matches_splitmix64() -> None:
    """The integers are SplitMix64's: word n of the stream keyed k is mix64(k + n * gamma), checked against the
    published generator written with Python integers (seeded 0, its first outputs)."""
    mask = (1 << 64) - 1

    def reference(state: int, count: int) -> list[int]:
        out = []
        for _ in range(count):
            state = (state + 0x9E3779B97F4A7C15) & mask
            z = state
            z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
            z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
            out.append(z ^ (z >> 31))
        return out

    for key in [0, 1, 0x0123456789ABCDEF, mask]:
        signed = key - (1 << 64) if key >= 1 << 63 else key
        words = stream_words(torch.tensor([[signed]], dtype=torch.int64), 5)[0]
        assert [int(w) & mask for w in words] == reference(key, 5)
    assert reference(0, 1) == [0xE220A8397B1DCDAF]  # SplitMix64 seeded 0: its well-known first output


@pytest.mark.parametrize("seeds", [[], [[1, 2]], [1.5], [-1], [2**64]])
def test_row_noise_rejects_bad_seeds(seeds: list) -> None:
    with pytest.raises(ValueError, match="seed"):
        RowNoise(seeds)


#: The batch-independence tests sample in float64. CPU convolutions and matmuls pick their kernels (and summation
#: order) by batch size and by CPU, so in float32 the same row differs between batches in its last bits, and a
#: sampler's steps amplify that by a factor that depends on the machine (up to 2.6e-4 seen on an AVX2-only CPU,
#: under 1e-4 on AVX-512 ones). In float64 that rounding is about 1e-16 and stays far below ``ROW_ATOL`` on any
#: CPU, while a row whose noise, conditions or guidance depended on its batch position would differ by order one.
DTYPE = torch.float64
ROW_ATOL = 1e-9


def assert_same_rows(a: torch.Tensor, b: torch.Tensor) -> None:
    """Equal up to float64 rounding (see ``ROW_ATOL``); samples from other noise differ by order one."""
    assert a.dtype == b.dtype == DTYPE
    torch.testing.assert_close(a, b, rtol=0.0, atol=ROW_ATOL)


def _bundle(obs_dim: int = OBS, act_dim: int = ACT, dtype: torch.dtype = DTYPE) -> ModelBundle:
    torch.manual_seed(0)
    normalizer = MinMaxNormalizer(-np.ones(obs_dim + act_dim), np.ones(obs_dim + act_dim))
    bundle = make_bundle(TINY, DIFFUSION, obs_dim, act_dim, normalizer)
    bundle.ema.to(dtype)
    return bundle


def _diffusion() -> GaussianDiffusion:
    return _bundle().ema.eval()


def test_the_float32_network_treats_each_row_alone() -> None:
    """The network itself (the one path the float64 tests cannot see in float32) mixes no rows: one call on a
    batch gives each row what it gives alone, up to one call's float32 rounding (about 1e-6; a network that mixed
    rows, e.g. by batch statistics, would differ by order one)."""
    diffusion = _bundle(dtype=torch.float32).ema.eval()
    x = torch.randn(5, H, OBS + ACT, generator=torch.Generator().manual_seed(0))
    t = torch.tensor([0, 3, 7, 5, 1])
    with torch.no_grad():
        batch = diffusion.model(x, t)
        for r in range(5):
            torch.testing.assert_close(diffusion.model(x[[r]], t[[r]]), batch[[r]], rtol=0.0, atol=1e-4)


def _guidance(kind: str, rows: list[int]) -> GuidanceBase | None:
    """Guidance of the given rows of the batch: none, toward each row's coin, or by a real value network."""
    if kind == "none":
        return None
    if kind == "coin":
        coins = torch.tensor([[0.5, -0.5], [-0.5, 0.5], [0.0, 0.8], [0.8, 0.0]], dtype=DTYPE)[rows]
        return Guidance(CoinObjective(coins), 0.5, lambda x: x[..., ACT:])
    torch.manual_seed(1)
    value = ValueNetwork(OBS + ACT, H, 8, (1, 2)).to(DTYPE).eval()
    return ValueGuidance(value, scale=0.5, n_guide_steps=2, t_stopgrad=0)


@pytest.mark.parametrize("guide", ["none", "coin", "value"])
@pytest.mark.parametrize("sampler", [DDPMSampler(), DDIMSampler(4)], ids=["ddpm", "ddim"])
def test_a_rows_sample_is_the_same_alone_and_in_any_batch(sampler: Sampler, guide: str) -> None:
    diffusion = _diffusion()
    g = torch.Generator().manual_seed(3)
    starts, goals = (torch.rand(4, OBS, generator=g, dtype=DTYPE) * 2 - 1 for _ in range(2))

    def draw(rows: list[int], guide: str = guide) -> torch.Tensor:
        conditions = {0: starts[rows], H - 1: goals[rows]}
        noise = RowNoise([SEEDS[r] for r in rows], dtype=DTYPE)
        return sampler.sample(diffusion, conditions, noise, _guidance(guide, rows))

    batch = draw([0, 1, 2, 3])
    assert batch.shape == (4, H, OBS + ACT) and not torch.equal(batch[0], batch[1])
    for r in range(4):
        assert_same_rows(draw([r]), batch[[r]])
    assert_same_rows(draw([3, 1, 0]), batch[[3, 1, 0]])
    if guide != "none":  # the guidance does act on every row
        unguided = draw([0, 1, 2, 3], "none")
        assert all(not torch.allclose(batch[r], unguided[r]) for r in range(4))


def test_sampler_and_planner_need_one_seed_per_row() -> None:
    diffusion = _diffusion()
    with pytest.raises(ValueError, match="3 rows but the noise has 2"):
        DDIMSampler(4).sample(diffusion, {0: torch.zeros(3, OBS)}, RowNoise([1, 2]))
    planner = Planner(_bundle(), DDIMSampler(4), CPU)
    with pytest.raises(ValueError, match="2 starts but 3 seeds"):
        planner.plan(np.zeros((2, OBS)), np.zeros((2, OBS)), [1, 2, 3])


def _same_episodes(a: EpisodeBatchResult, b: EpisodeBatchResult, return_rtol: float = 0.0) -> None:
    """Episode by episode the same returns and lengths, and the same first plans up to float32 rounding (see
    :func:`assert_same_rows`; plans from other noise differ by order one)."""
    assert a.episodes == b.episodes and a.lengths == b.lengths
    np.testing.assert_allclose(a.returns, b.returns, rtol=return_rtol, atol=0.0)
    for x, y in zip(a.plans, b.plans, strict=True):
        np.testing.assert_allclose(x, y, rtol=0.0, atol=1e-3)


def test_maze2d_evaluation_does_not_depend_on_the_batch_size(tmp_path: Path) -> None:
    params = Params()
    task = params.resolve("maze2d-umaze")
    family = get_family(task.family)
    sim = family.make_simulator(task)
    bundle = _bundle(sim.obs_dim, sim.act_dim)
    # plans at t = 0, 100 and 200, so the seeds of later steps are checked too
    task = dataclasses.replace(task, planner=dataclasses.replace(task.planner, replan_every=100))

    def evaluate(batch_size: int) -> EpisodeBatchResult:
        planner = Planner(bundle, DDIMSampler(4), CPU)
        controller = family.controller(task, planner, TaskFiles(tmp_path, task.name), CPU)
        return run_episodes(
            lambda: family.make_simulator(task), controller, 3, task.evaluate.seed, batch_size, progress=False
        )

    alone = evaluate(1)
    # Maze2D's reward counts the steps spent at the goal: rounding-level differences of the plans (about 1e-5)
    # move the tracked states by about 1e-6, far from changing a count, so the returns are compared exactly
    for batch_size in (3, 2):
        other = evaluate(batch_size)
        _same_episodes(alone, other)
        for x, y in zip(alone.executed, other.executed, strict=True):
            np.testing.assert_allclose(x, y, rtol=0.0, atol=1e-4)


def test_locomotion_evaluation_does_not_depend_on_the_batch_size(tmp_path: Path) -> None:
    raw = yaml.safe_load(apply_profile("smoke", PROFILES, tmp_path / "params.yaml").read_text())
    task = params_from_dict(raw).resolve("hopper-medium")  # 40 steps, n_samples 2, horizon 16, DDPM 8 steps
    family = get_family(task.family)
    sim = family.make_simulator(task)
    dim = sim.obs_dim + sim.act_dim
    torch.manual_seed(0)
    bundle = make_bundle(task.model, task.diffusion, sim.obs_dim, sim.act_dim,
                         GaussianNormalizer(np.zeros(dim), np.ones(dim)), conditioning="start")  # fmt: skip
    vm = task.settings.value_model
    files = TaskFiles(tmp_path, task.name)
    save_value(files.value, ValueNetwork(dim, task.diffusion.horizon, vm.dim, tuple(vm.dim_mults)))

    def evaluate(batch_size: int) -> EpisodeBatchResult:
        planner = Planner(bundle, DDPMSampler(), CPU)
        controller = family.controller(task, planner, files, CPU)
        return run_episodes(
            lambda: family.make_simulator(task), controller, 3, task.evaluate.seed, batch_size, progress=False
        )

    # Hopper's contacts amplify the rounding-level differences of the plans (see assert_same_rows) along the
    # episode, so the returns agree to a relative 1e-3 rather than exactly (they differ by about 3e-5 here)
    _same_episodes(evaluate(1), evaluate(3), return_rtol=1e-3)


def test_generated_plans_do_not_depend_on_the_batch_size() -> None:
    env = maze_sim()
    rng = np.random.default_rng(2)
    tasks = add_coins(env, sample_navigation_tasks(env, 5, rng), 0.4, rng)
    assert 0 < tasks.has_coin().sum() < 5  # plain and coin-guided batches both
    planner = Planner(_bundle(env.obs_dim, env.act_dim), DDIMSampler(4), CPU)
    one = generate_plans(planner, tasks, batch_size=1, seed=3, alpha=0.5, progress=False)
    for batch_size in (2, 5):
        batched = generate_plans(planner, tasks, batch_size=batch_size, seed=3, alpha=0.5, progress=False)
        assert_same_rows(torch.as_tensor(batched), torch.as_tensor(one))
    assert not np.allclose(one, generate_plans(planner, tasks, batch_size=5, seed=4, alpha=0.5, progress=False))


def test_gold_coin_plans_with_and_without_guidance_share_their_noise() -> None:
    """The evaluate-unseen stage draws its unguided pictures with the controller's seeds of t = 0: guidance of
    scale zero gives back exactly those plans, and a real scale moves them."""
    envs = [maze_sim() for _ in range(3)]
    obs = np.stack([env.reset(np.random.default_rng(i)) for i, env in enumerate(envs)])
    goals = np.stack([env.goal_state() for env in envs])
    coins = torch.tensor([[1.0, -1.0], [1.0, 1.0], [-1.0, -1.0]])
    planner = Planner(_bundle(), DDIMSampler(4), CPU)
    plain = planner.plan(obs, goals, PlannerController(planner, seed=9).seeds([0, 1, 2], 0))[:, :, ACT:]
    for alpha in (0.0, 5.0):

        def guide(episodes: list[int], alpha: float = alpha) -> Guidance:
            return planner.guidance(CoinObjective(coins[episodes]), alpha)

        controller = PlannerController(planner, seed=9, guidance_for=guide)
        controller.begin(envs, obs, [0, 1, 2])
        controller.act(envs, obs, 0)
        assert np.array_equal(controller.first_plans, plain) == (alpha == 0.0)
