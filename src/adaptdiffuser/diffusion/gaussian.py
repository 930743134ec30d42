"""Gaussian diffusion over trajectories: cosine schedule, forward noising, the training loss, posteriors."""

from __future__ import annotations

import math

import torch
from torch import nn

from adaptdiffuser.diffusion.conditions import Conditions, apply_inpainting


def cosine_betas(n_steps: int, s: float = 0.008, max_beta: float = 0.999) -> torch.Tensor:
    """The cosine noise schedule (Nichol & Dhariwal 2021), betas clipped to ``max_beta``."""
    steps = torch.arange(n_steps + 1, dtype=torch.float64)
    f = torch.cos(((steps / n_steps) + s) / (1 + s) * math.pi / 2) ** 2
    alphas_cumprod = f / f[0]
    betas = 1 - alphas_cumprod[1:] / alphas_cumprod[:-1]
    return betas.clamp(max=max_beta)


class GaussianDiffusion(nn.Module):
    """The diffusion process around a denoiser network that predicts x0 (or epsilon)."""

    def __init__(
        self,
        model: nn.Module,
        horizon: int,
        obs_dim: int,
        act_dim: int,
        n_steps: int = 64,
        predict_epsilon: bool = False,
        clip_denoised: bool = True,
        action_weight: float = 1.0,
        loss_discount: float = 1.0,
    ) -> None:
        super().__init__()
        self.model = model
        self.horizon = horizon
        self.obs_dim = obs_dim
        self.act_dim = act_dim
        self.transition_dim = obs_dim + act_dim
        self.n_steps = n_steps
        self.predict_epsilon = predict_epsilon
        self.clip_denoised = clip_denoised

        betas = cosine_betas(n_steps)
        alphas_cumprod = torch.cumprod(1 - betas, dim=0)
        prev = torch.cat([torch.ones(1, dtype=torch.float64), alphas_cumprod[:-1]])
        posterior_var = betas * (1 - prev) / (1 - alphas_cumprod)
        buffers = {
            "betas": betas,
            "alphas_cumprod": alphas_cumprod,
            "alphas_cumprod_prev": prev,
            "sqrt_alphas_cumprod": alphas_cumprod.sqrt(),
            "sqrt_one_minus_alphas_cumprod": (1 - alphas_cumprod).sqrt(),
            "posterior_variance": posterior_var,
            "posterior_log_variance": posterior_var.clamp(min=1e-20).log(),
            "posterior_mean_coef_x0": betas * prev.sqrt() / (1 - alphas_cumprod),
            "posterior_mean_coef_xt": (1 - prev) * (1 - betas).sqrt() / (1 - alphas_cumprod),
        }
        for name, value in buffers.items():
            self.register_buffer(name, value.float(), persistent=False)

        weights = loss_discount ** torch.arange(horizon, dtype=torch.float32)[:, None]
        weights = weights.repeat(1, self.transition_dim)
        weights = weights / weights.mean()
        weights[0, :act_dim] = action_weight
        self.register_buffer("loss_weights", weights, persistent=False)

    @staticmethod
    def _at(values: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return values[t][:, None, None]

    def q_sample(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Noise clean trajectories ``x0`` to step ``t``."""
        return self._at(self.sqrt_alphas_cumprod, t) * x0 + self._at(self.sqrt_one_minus_alphas_cumprod, t) * noise

    def predict_x0(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The network's estimate of the clean trajectory from ``x`` at step ``t`` (clipped if configured)."""
        out = self.model(x, t)
        if self.predict_epsilon:
            out = (x - self._at(self.sqrt_one_minus_alphas_cumprod, t) * out) / self._at(self.sqrt_alphas_cumprod, t)
        if self.clip_denoised:
            out = out.clamp(-1.0, 1.0)
        return out

    def posterior(self, x0: torch.Tensor, xt: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-variance of q(x_{t-1} | x_t, x_0)."""
        mean = self._at(self.posterior_mean_coef_x0, t) * x0 + self._at(self.posterior_mean_coef_xt, t) * xt
        return mean, self._at(self.posterior_log_variance, t)

    def loss(self, x0: torch.Tensor, conditions: Conditions, generator: torch.Generator | None = None) -> torch.Tensor:
        """Weighted L2 denoising loss on a batch of normalized trajectories."""
        batch = x0.shape[0]
        t = torch.randint(0, self.n_steps, (batch,), device=x0.device, generator=generator)
        noise = torch.randn(x0.shape, device=x0.device, generator=generator)
        xt = apply_inpainting(self.q_sample(x0, t, noise), conditions, self.act_dim)
        pred = self.model(xt, t)
        if self.predict_epsilon:
            target = noise
        else:
            pred = apply_inpainting(pred, conditions, self.act_dim)
            target = x0
        return ((pred - target) ** 2 * self.loss_weights).mean()
