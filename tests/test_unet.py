"""The temporal U-Net: shapes, the paper's size, horizon checks and conditioning on the diffusion step."""

from __future__ import annotations

import math

import pytest
import torch

from adaptdiffuser.models.unet import SinusoidalEmbedding, TemporalUnet


def n_params(net: torch.nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


@pytest.mark.parametrize(
    ("transition", "dim", "mults", "horizon"),
    [(6, 8, (1, 2, 4), 32), (6, 16, (1, 4, 8), 128), (3, 8, (1, 2), 12), (6, 8, (1, 4, 8), 100)],
)
def test_output_shape_equals_input_shape(transition: int, dim: int, mults: tuple[int, ...], horizon: int) -> None:
    torch.manual_seed(0)
    net = TemporalUnet(transition, dim=dim, dim_mults=mults)
    x = torch.randn(3, horizon, transition)
    out = net(x, torch.tensor([0, 5, 63]))
    assert out.shape == x.shape
    assert torch.isfinite(out).all()


def test_paper_network_size() -> None:
    net = TemporalUnet(6, dim=32, dim_mults=(1, 4, 8))
    assert 3.6e6 <= n_params(net) <= 3.75e6  # the paper reports 3.68 M
    assert n_params(TemporalUnet(6, dim=16, dim_mults=(1, 4, 8))) < n_params(net) / 3


@pytest.mark.parametrize(("mults", "horizon"), [((1, 2, 4), 30), ((1, 4, 8), 102), ((1, 2), 15)])
def test_horizon_not_divisible_raises(mults: tuple[int, ...], horizon: int) -> None:
    net = TemporalUnet(6, dim=8, dim_mults=mults)
    with pytest.raises(ValueError, match=f"horizon {horizon}"):
        net(torch.randn(1, horizon, 6), torch.zeros(1, dtype=torch.long))


@pytest.mark.parametrize(("mults", "horizon"), [((1, 4, 8), 24), ((1, 2, 4, 8), 40), ((1, 2), 6), ((1,), 7)])
def test_each_level_halves_the_horizon_and_the_output_restores_it(mults: tuple[int, ...], horizon: int) -> None:
    """Level ``i`` of the contracting path works on ``horizon / 2^i`` steps, the middle on ``horizon /
    downsample_factor``, and the expanding path brings it back; any multiple of the factor is accepted."""
    net = TemporalUnet(3, dim=8, dim_mults=mults)
    assert net.downsample_factor == 2 ** (len(mults) - 1)
    lengths: dict[str, int] = {}

    def record(name: str):
        def hook(module: torch.nn.Module, args: tuple, out: torch.Tensor) -> None:
            lengths[name] = out.shape[-1]

        return hook

    for i, (_, block2, _) in enumerate(net.down):
        block2.register_forward_hook(record(f"down{i}"))
    net.mid2.register_forward_hook(record("mid"))
    for i, (_, block2, _) in enumerate(net.up):
        block2.register_forward_hook(record(f"up{i}"))
    with torch.no_grad():
        out = net(torch.randn(2, horizon, 3), torch.tensor([0, 3]))
    assert out.shape == (2, horizon, 3)
    levels = len(mults)
    assert [lengths[f"down{i}"] for i in range(levels)] == [horizon // 2**i for i in range(levels)]
    assert lengths["mid"] == horizon // net.downsample_factor
    # the expanding path joins each skip at its own length, then doubles it
    assert [lengths[f"up{i}"] for i in range(levels - 1)] == [
        horizon // 2 ** (levels - 1 - i) for i in range(levels - 1)
    ]


def test_output_depends_on_diffusion_step() -> None:
    torch.manual_seed(0)
    net = TemporalUnet(6, dim=8, dim_mults=(1, 2))
    x = torch.randn(1, 16, 6).repeat(3, 1, 1)
    with torch.no_grad():
        out = net(x, torch.tensor([0, 1, 7]))
    assert not torch.allclose(out[0], out[1], atol=1e-6)
    assert not torch.allclose(out[0], out[2], atol=1e-6)
    with torch.no_grad():
        again = net(x[:1], torch.tensor([1]))
    # alone vs in a batch of 3: one call's float32 rounding (about 1e-6; kernels differ by batch size and CPU)
    torch.testing.assert_close(again[0], out[1], rtol=0.0, atol=1e-4)


def test_batch_elements_are_independent() -> None:
    """GroupNorm normalizes per sample, so one trajectory's output does not depend on the rest of the batch."""
    torch.manual_seed(0)
    net = TemporalUnet(6, dim=8, dim_mults=(1, 2))
    x = torch.randn(4, 16, 6)
    t = torch.tensor([3, 3, 3, 3])
    with torch.no_grad():
        full = net(x, t)
        x2 = x.clone()
        x2[1:] = torch.randn(3, 16, 6) * 10
        changed = net(x2, t)
    torch.testing.assert_close(changed[0], full[0], rtol=1e-5, atol=1e-5)
    assert not torch.allclose(changed[1], full[1])


@pytest.mark.parametrize("dim", [16, 6])
def test_sinusoidal_embedding_is_the_closed_form(dim: int) -> None:
    """``emb(t) = [sin(t w_0), ..., sin(t w_{h-1}), cos(t w_0), ..., cos(t w_{h-1})]`` with ``h = dim / 2`` and
    ``w_i = 10000^(-i / (h - 1))``: frequencies from 1 down to 1 / 10000."""
    steps = [0, 1, 2, 7, 63, 999]
    emb = SinusoidalEmbedding(dim)(torch.tensor(steps)).double()
    half = dim // 2
    freqs = [10000 ** (-i / (half - 1)) for i in range(half)]
    expected = torch.tensor(
        [[math.sin(t * w) for w in freqs] + [math.cos(t * w) for w in freqs] for t in steps], dtype=torch.float64
    )
    assert emb.shape == (len(steps), dim)
    torch.testing.assert_close(emb, expected, rtol=0, atol=2e-4)  # float32 angles up to 999 rad
    # the first channel is sin(t), the slowest sin(t / 10000)
    torch.testing.assert_close(emb[:, 0], torch.sin(torch.tensor(steps, dtype=torch.float64)), rtol=0, atol=2e-4)
    assert emb[-1, half - 1].item() == pytest.approx(math.sin(999 / 10000), abs=1e-6)
