"""The samplers' math against a closed-form case.

Data are one Gaussian, every transition column ``d`` independently ``N(mu_d, sigma_d^2)``. For
``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps`` the minimum-MSE denoiser is known exactly:
``E[x0 | x_t] = mu + sqrt(abar_t) sigma^2 / (abar_t sigma^2 + 1 - abar_t) * (x_t - sqrt(abar_t) mu)`` and
``E[eps | x_t] = sqrt(1 - abar_t) / (abar_t sigma^2 + 1 - abar_t) * (x_t - sqrt(abar_t) mu)``. The project's DDPM and
DDIM samplers, run around that denoiser (as x0 or as epsilon prediction), must then draw samples whose mean and
variance are those of the data, up to the sampling error of the sample count and the samplers' known discretization
gap, which the moments of the ideal discretized chain (computed here from the schedule alone) give exactly.

Reward guidance around the same denoiser must move samples toward what the objective prefers, and scale 0 must be
exactly unguided sampling.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from adaptdiffuser.diffusion.gaussian import GaussianDiffusion
from adaptdiffuser.diffusion.guidance import Guidance, Objective
from adaptdiffuser.diffusion.noise import RowNoise
from adaptdiffuser.diffusion.samplers import DDIMSampler, DDPMSampler, Sampler

ACT, OBS = 2, 2
MU = (0.6, -1.3, 2.0, 0.0)  # per transition column [action, observation]; beyond [-1, 1], so clipping is off
SIGMA = (0.5, 0.8, 1.5, 1.0)
ROWS, HORIZON = 32, 1024  # the horizon's steps are independent draws too: 32 * 1023 samples per column
N_STEPS = 500
DDIM_STEPS = 125
Z = 4.5  # tolerance in standard errors: seeded runs; a correct sampler misses it for ~1 seed in 10^5


class GaussianOptimalDenoiser(nn.Module):
    """The exact conditional expectation of x0 (or of the noise) given ``x_t`` for Gaussian data, with the call
    signature of the project's denoiser network: ``forward(x [batch, horizon, transition], t [batch])``. Both are
    affine in ``x_t``; their slope and offset per step and column are tabulated (in float64) once."""

    def __init__(
        self, mu: torch.Tensor, sigma: torch.Tensor, alphas_cumprod: torch.Tensor, predict_epsilon: bool
    ) -> None:
        super().__init__()
        mu, var, ab = mu.double(), sigma.double() ** 2, alphas_cumprod.double()[:, None]
        total = ab * var + 1 - ab  # the variance of x_t, [n_steps, transition]
        if predict_epsilon:  # E[eps | x_t] = sqrt(1 - ab) / total * (x_t - sqrt(ab) mu)
            slope = (1 - ab).sqrt() / total
            offset = -slope * ab.sqrt() * mu
        else:  # E[x0 | x_t] = mu + sqrt(ab) var / total * (x_t - sqrt(ab) mu)
            slope = ab.sqrt() * var / total
            offset = mu - slope * ab.sqrt() * mu
        self.register_buffer("slope", slope.float())
        self.register_buffer("offset", offset.float())

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return self.slope[t][:, None, :] * x + self.offset[t][:, None, :]


def gaussian_diffusion(predict_epsilon: bool, n_steps: int = N_STEPS) -> GaussianDiffusion:
    """The project's diffusion process around the optimal denoiser of ``N(MU, diag(SIGMA^2))``, unclipped."""
    diff = GaussianDiffusion(
        nn.Identity(), HORIZON, OBS, ACT, n_steps=n_steps, predict_epsilon=predict_epsilon, clip_denoised=False
    )
    diff.model = GaussianOptimalDenoiser(
        torch.tensor(MU), torch.tensor(SIGMA), diff.alphas_cumprod, predict_epsilon=predict_epsilon
    )
    return diff.eval()


def ideal_moments(abar: np.ndarray, steps: list[int], stochastic: bool) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance per column of the ideal discretized chain (DDPM posterior steps or DDIM eta = 0 jumps)
    around the optimal denoiser, from ``x_T ~ N(0, 1)``: every step is affine in ``x_t`` plus Gaussian noise, so
    the moments propagate exactly. Written from the schedule alone, not from the sampler's code."""
    mu, var = np.asarray(MU), np.asarray(SIGMA) ** 2
    mean, variance = np.zeros(len(MU)), np.ones(len(MU))
    for t, t_prev in zip(steps, [*steps[1:], -1], strict=True):
        ab, ab_prev = abar[t], (abar[t_prev] if t_prev >= 0 else 1.0)
        gain = math.sqrt(ab) * var / (ab * var + 1 - ab)  # x0_hat = mu + gain * (x_t - sqrt(ab) mu)
        x0_slope, x0_offset = gain, mu * (1 - gain * math.sqrt(ab))
        if stochastic:  # q(x_{t-1} | x_t, x0_hat) with beta_t = 1 - abar_t / abar_{t-1}
            beta = 1 - ab / ab_prev
            c_x0 = math.sqrt(ab_prev) * beta / (1 - ab)
            c_xt = math.sqrt(1 - beta) * (1 - ab_prev) / (1 - ab)
            slope, offset, noise = c_x0 * x0_slope + c_xt, c_x0 * x0_offset, beta * (1 - ab_prev) / (1 - ab)
        else:  # x_prev = sqrt(ab_prev) x0_hat + sqrt(1 - ab_prev) eps_hat, eps_hat = (x_t - sqrt(ab) x0_hat) / ...
            eps_slope = (1 - math.sqrt(ab) * x0_slope) / math.sqrt(1 - ab)
            eps_offset = -math.sqrt(ab) * x0_offset / math.sqrt(1 - ab)
            slope = math.sqrt(ab_prev) * x0_slope + math.sqrt(1 - ab_prev) * eps_slope
            offset = math.sqrt(ab_prev) * x0_offset + math.sqrt(1 - ab_prev) * eps_offset
            noise = 0.0
        mean, variance = slope * mean + offset, slope**2 * variance + noise
    return mean, variance


SAMPLERS = {"ddpm": DDPMSampler, "ddim": lambda: DDIMSampler(DDIM_STEPS)}


def conditions() -> dict[int, torch.Tensor]:
    """Every plan starts at the same, far-from-typical state (inpainting composes with the closed form: the
    columns are independent, so pinning step 0 leaves the other steps' distribution alone)."""
    return {0: torch.tensor([[5.0, -5.0]]).repeat(ROWS, 1)}


@pytest.mark.parametrize("predict_epsilon", [False, True], ids=["x0", "epsilon"])
@pytest.mark.parametrize("kind", sorted(SAMPLERS))
def test_samplers_draw_the_data_distribution_with_the_optimal_denoiser(kind: str, predict_epsilon: bool) -> None:
    diff = gaussian_diffusion(predict_epsilon)
    sampler: Sampler = SAMPLERS[kind]()
    cond = conditions()
    x = sampler.sample(diff, cond, RowNoise(range(ROWS)))
    assert x.shape == (ROWS, HORIZON, ACT + OBS) and not x.requires_grad
    assert torch.equal(x[:, 0, ACT:], cond[0])

    samples = x[:, 1:].reshape(-1, ACT + OBS).double().numpy()
    n = len(samples)
    mean, var = samples.mean(0), samples.var(0, ddof=1)
    abar = diff.alphas_cumprod.double().numpy()
    ideal_mean, ideal_var = ideal_moments(abar, sampler.timesteps(diff), stochastic=kind == "ddpm")
    mu, sigma2 = np.asarray(MU), np.asarray(SIGMA) ** 2
    # the ideal chain is within its discretization gap of the data (a property of the schedule and step count)
    np.testing.assert_allclose(ideal_mean, mu, atol=1e-3)
    gap = np.abs(ideal_var / sigma2 - 1)
    assert gap.max() < 0.03, gap
    # the sampler draws the ideal chain's distribution, up to the sampling error of n draws
    mean_tol = Z * np.sqrt(ideal_var / n)
    var_tol = Z * np.sqrt(2 / (n - 1))  # relative standard error of a Gaussian sample variance
    assert np.all(np.abs(mean - ideal_mean) <= mean_tol), (mean, ideal_mean, mean_tol)
    assert np.all(np.abs(var / ideal_var - 1) <= var_tol), (var, ideal_var, var_tol)
    # hence the data's moments, within the sampling error plus the known gap
    assert np.all(np.abs(mean - mu) <= mean_tol + 1e-3), (mean, mu)
    assert np.all(np.abs(var / sigma2 - 1) <= var_tol + gap), (var, sigma2)


def test_optimal_denoiser_is_the_regression_of_x0_on_x_t() -> None:
    """The hand-written denoiser is the least-squares predictor of x0 (and of the noise) from the project's own
    forward noising, so the sampler tests above run around the true optimum."""
    g = torch.Generator().manual_seed(0)
    x0 = torch.tensor(MU) + torch.tensor(SIGMA) * torch.randn(8, HORIZON, ACT + OBS, generator=g)
    noise = torch.randn(x0.shape, generator=g)
    for predict_epsilon, target in ((False, x0), (True, noise)):
        diff = gaussian_diffusion(predict_epsilon)
        for step in (0, N_STEPS // 3, N_STEPS - 2):
            t = torch.full((8,), step)
            xt = diff.q_sample(x0, t, noise)
            pred = diff.model(xt, t)
            # column by column, it predicts as well as the least-squares line fitted to these very samples
            for d in range(ACT + OBS):
                a, b = xt[..., d].flatten().double(), target[..., d].flatten().double()
                slope = ((a - a.mean()) * (b - b.mean())).sum() / ((a - a.mean()) ** 2).sum()
                fitted = b.mean() + slope * (a - a.mean())
                residual = (b - fitted).pow(2).mean()
                assert (b - pred[..., d].flatten().double()).pow(2).mean() <= residual * 1.01 + 1e-4


class PullColumn(Objective):
    """``J = -sum_t (s_t[column] - target)^2``: a reward that prefers plans whose state column sits at ``target``."""

    def __init__(self, column: int, target: float) -> None:
        self.column, self.target = column, target

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        return -((states[..., self.column] - self.target) ** 2).sum(-1)


TARGET = 3.0  # for observation column 1, whose data are N(0, 1): 3 standard deviations away


def _distance_to_target(x: torch.Tensor) -> float:
    return float((x[:, 1:, ACT + 1] - TARGET).abs().mean())


@pytest.mark.parametrize("predict_epsilon", [False, True], ids=["x0", "epsilon"])
@pytest.mark.parametrize("kind", sorted(SAMPLERS))
def test_reward_guidance_moves_samples_toward_the_objective(kind: str, predict_epsilon: bool) -> None:
    diff = gaussian_diffusion(predict_epsilon, n_steps=64)
    sampler: Sampler = DDPMSampler() if kind == "ddpm" else DDIMSampler(16)
    rows = 8
    cond = {0: conditions()[0][:rows]}

    def draw(alpha: float | None) -> torch.Tensor:
        guidance = None if alpha is None else Guidance(PullColumn(1, TARGET), alpha, lambda x: x[..., ACT:])
        return sampler.sample(diff, cond, RowNoise(range(rows)), guidance=guidance)

    plain = draw(None)
    assert torch.equal(draw(None), plain)  # seeded: the same draw again
    assert torch.equal(draw(0.0), plain)  # scale 0 is exactly unguided sampling
    toward, away = draw(1.0), draw(-1.0)
    d_plain, d_toward, d_away = map(_distance_to_target, (plain, toward, away))
    assert d_plain > 2.5  # unguided, column 1 stays around its data mean 0
    assert d_toward < d_plain / 3, (d_toward, d_plain)
    assert d_away > d_plain + 0.5, (d_away, d_plain)
    # the objective's gradient touches only its column: the others are drawn exactly as unguided
    assert torch.equal(toward[..., :-1], plain[..., :-1])
    assert torch.equal(toward[:, 0, ACT:], cond[0])  # and the inpainted start stays pinned
