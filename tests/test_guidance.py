"""Reward-gradient guidance toward a gold coin: alpha = 0 is exactly unguided sampling, a positive alpha brings
plans closer to the coin, and guidance composes with inpainting. Value guidance (Diffuser's locomotion recipe)
with a hand-built differentiable value raises that value in both samplers, also with inpainting."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from adaptdiffuser.checkpoint import ModelBundle, make_bundle
from adaptdiffuser.config import DiffusionParams, ModelParams, PretrainParams
from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.data.schema import Trajectories
from adaptdiffuser.data.windows import WindowDataset, joint_array
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.diffusion.guidance import Guidance, ValueGuidance
from adaptdiffuser.diffusion.samplers import DDIMSampler, DDPMSampler
from adaptdiffuser.families.maze2d.gold_coin import CoinObjective
from adaptdiffuser.planning import Planner
from adaptdiffuser.training import train

CPU = torch.device("cpu")
# U-Maze: from the top-right cell to the goal at the top-left; the coin lies behind the start, bottom right
STARTS = np.tile([[1.0, 1.0, 0.0, 0.0]], (6, 1))
GOALS = np.tile([[-1.0, 1.0, 0.0, 0.0]], (6, 1))
COIN = torch.tensor([[1.0, -1.0]]).repeat(6, 1)
SEEDS = [derive_seed(3, i) for i in range(6)]  # one per plan: the same start and goal, six different noises


@pytest.fixture(scope="module")
def trained(expert_traj: Trajectories) -> ModelBundle:
    """A tiny model trained briefly on real expert data (enough for its denoiser to follow its input)."""
    torch.manual_seed(0)
    normalizer = MinMaxNormalizer.fit(joint_array(expert_traj))
    bundle = make_bundle(
        ModelParams(dim=8, dim_mults=[1, 2]),
        DiffusionParams(horizon=32, n_steps=16, predict_epsilon=True),
        4,
        2,
        normalizer,
    )
    cfg = PretrainParams(steps=300, batch_size=16, ema_start=0, ema_every=1, ema_decay=0.9, log_every=100)
    train(bundle, WindowDataset(expert_traj, 32, normalizer), cfg, CPU, progress=False)
    return bundle


def _closest_approach(plans: np.ndarray) -> np.ndarray:
    return np.linalg.norm(plans[:, :, 2:4] - COIN.numpy()[:, None, :], axis=-1).min(axis=1)


@pytest.mark.parametrize("on", ["mean", "x0"])
@pytest.mark.parametrize("sampler", [DDPMSampler(), DDIMSampler(8)], ids=["ddpm", "ddim"])
def test_alpha_zero_is_exactly_unguided(trained: ModelBundle, sampler, on: str) -> None:
    planner = Planner(trained, sampler, CPU)
    plain = planner.plan(STARTS, GOALS, SEEDS)
    zero = planner.plan(STARTS, GOALS, SEEDS, guidance=planner.guidance(CoinObjective(COIN), 0.0, on))
    np.testing.assert_array_equal(plain, zero)


@pytest.mark.parametrize(("on", "alpha"), [("mean", 10.0), ("x0", 0.1)])
@pytest.mark.parametrize("sampler", [DDPMSampler(), DDIMSampler(8)], ids=["ddpm", "ddim"])
def test_guidance_moves_plans_toward_the_coin_and_keeps_inpainting(
    trained: ModelBundle, sampler, on: str, alpha: float
) -> None:
    """On the step's mean (the paper's) or on the clean estimate, guidance pulls plans toward the coin."""
    planner = Planner(trained, sampler, CPU)
    plain = planner.plan(STARTS, GOALS, SEEDS)
    guided = planner.plan(STARTS, GOALS, SEEDS, guidance=planner.guidance(CoinObjective(COIN), alpha, on))
    assert _closest_approach(guided).mean() < _closest_approach(plain).mean() - 0.1
    # the start and goal stay pinned by inpainting
    np.testing.assert_allclose(guided[:, 0, 2:], STARTS, atol=1e-5)
    np.testing.assert_allclose(guided[:, -1, 2:], GOALS, atol=1e-5)
    # and a negative alpha pushes the other way
    away = planner.plan(STARTS, GOALS, SEEDS, guidance=planner.guidance(CoinObjective(COIN), -alpha, on))
    assert _closest_approach(away).mean() > _closest_approach(guided).mean()


def test_coin_objective_is_the_negative_summed_distance() -> None:
    states = torch.tensor([[[0.0, 0.0, 5.0, 5.0], [3.0, 4.0, 0.0, 0.0]]])
    value = CoinObjective(torch.zeros(1, 2))(states)
    assert value.shape == (1,) and value.item() == pytest.approx(-5.0, abs=1e-5)
    # its gradient points each state toward the coin
    x = states.clone().requires_grad_(True)
    CoinObjective(torch.zeros(1, 2))(x).sum().backward()
    np.testing.assert_allclose(x.grad[0, 1, :2].numpy(), [-0.6, -0.8], atol=1e-5)


class MeanOfDim(nn.Module):
    """A stand-in value network: the mean over the horizon of one dimension of the normalized trajectory."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return x[..., self.dim].mean(dim=1)


Y = 3  # the y position: act_dim 2 + observation index 1


@pytest.mark.parametrize("sampler", [DDPMSampler(), DDIMSampler(8)], ids=["ddpm", "ddim"])
def test_value_guidance_raises_the_value_and_keeps_inpainting(trained: ModelBundle, sampler) -> None:
    planner = Planner(trained, sampler, CPU)
    plain = planner.plan(STARTS, GOALS, SEEDS)
    up = ValueGuidance(MeanOfDim(Y), scale=10.0, n_guide_steps=2, t_stopgrad=0)
    guided = planner.plan(STARTS, GOALS, SEEDS, guidance=up)
    assert guided[:, :, Y].mean() > plain[:, :, Y].mean() + 0.2
    down = planner.plan(STARTS, GOALS, SEEDS, guidance=ValueGuidance(MeanOfDim(Y), -10.0, 2, t_stopgrad=0))
    assert down[:, :, Y].mean() < plain[:, :, Y].mean() - 0.2
    for plans in (guided, down):
        np.testing.assert_allclose(plans[:, 0, 2:], STARTS, atol=1e-5)
        np.testing.assert_allclose(plans[:, -1, 2:], GOALS, atol=1e-5)
    # the values of the finished samples, to pick the best of N: here exactly the normalized mean y
    normed = torch.as_tensor(trained.normalizer.normalize(guided), dtype=torch.float32)
    values = up.values(normed)
    assert values.shape == (len(STARTS),)
    torch.testing.assert_close(values, normed[..., Y].mean(1))
    # guidance stopped at every step (t_stopgrad = n_steps) is exactly unguided sampling
    n_steps = trained.ema.n_steps
    off = ValueGuidance(MeanOfDim(Y), scale=10.0, n_guide_steps=2, t_stopgrad=n_steps)
    np.testing.assert_array_equal(planner.plan(STARTS, GOALS, SEEDS, guidance=off), plain)


def test_guidance_refuses_an_unknown_target() -> None:
    with pytest.raises(ValueError, match="'mean' or 'x0'"):
        Guidance(CoinObjective(COIN), 1.0, lambda x: x, on="noise")
