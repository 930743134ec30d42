"""The temporal U-Net: shapes, the paper's size, horizon checks and conditioning on the diffusion step."""

from __future__ import annotations

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


def test_downsample_factor() -> None:
    assert TemporalUnet(6, dim=8, dim_mults=(1, 4, 8)).downsample_factor == 4
    assert TemporalUnet(6, dim=8, dim_mults=(1,)).downsample_factor == 1


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
    torch.testing.assert_close(again[0], out[1], rtol=1e-5, atol=1e-5)


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


def test_sinusoidal_embedding() -> None:
    emb = SinusoidalEmbedding(16)(torch.tensor([0, 1, 10]))
    assert emb.shape == (3, 16)
    torch.testing.assert_close(emb[0, :8], torch.zeros(8))
    torch.testing.assert_close(emb[0, 8:], torch.ones(8))
    assert not torch.allclose(emb[1], emb[2])
