"""Per-dimension normalizers: ranges, round trips for numpy and torch, saving, degenerate dimensions."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from adaptdiffuser.data.normalizer import GaussianNormalizer, MinMaxNormalizer, Normalizer


@pytest.fixture
def data(rng: np.random.Generator) -> np.ndarray:
    """Dimensions with very different scales and offsets."""
    return rng.normal(size=(500, 5)) * np.array([0.01, 1.0, 30.0, 2.0, 5.0]) + np.array([0.0, -3.0, 100.0, 7.0, 0.5])


def test_minmax_maps_fitted_data_into_unit_box(data: np.ndarray) -> None:
    norm = MinMaxNormalizer.fit(data)
    out = norm.normalize(data)
    assert out.shape == data.shape
    assert out.min() >= -1.0 - 1e-12 and out.max() <= 1.0 + 1e-12
    np.testing.assert_allclose(out.min(axis=0), -1.0, atol=1e-12)
    np.testing.assert_allclose(out.max(axis=0), 1.0, atol=1e-12)
    # the argmin / argmax rows map exactly to the corners, dimension by dimension
    for d in range(data.shape[1]):
        assert out[data[:, d].argmin(), d] == pytest.approx(-1.0)
        assert out[data[:, d].argmax(), d] == pytest.approx(1.0)


@pytest.mark.parametrize("cls", [MinMaxNormalizer, GaussianNormalizer])
def test_round_trip_numpy(cls: type[Normalizer], data: np.ndarray) -> None:
    norm = cls.fit(data)
    np.testing.assert_allclose(norm.unnormalize(norm.normalize(data)), data, rtol=1e-10, atol=1e-10)
    assert not np.allclose(norm.normalize(data), data)


@pytest.mark.parametrize("cls", [MinMaxNormalizer, GaussianNormalizer])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_round_trip_torch(cls: type[Normalizer], data: np.ndarray, dtype: torch.dtype) -> None:
    norm = cls.fit(data)
    x = torch.as_tensor(data, dtype=dtype)
    y = norm.normalize(x)
    assert isinstance(y, torch.Tensor) and y.dtype == dtype and y.shape == x.shape
    # torch and numpy paths agree
    np.testing.assert_allclose(y.numpy(), norm.normalize(data), rtol=1e-5, atol=1e-5)
    back = norm.unnormalize(y)
    assert isinstance(back, torch.Tensor) and back.dtype == dtype
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(back, x, rtol=tol, atol=tol * 100)


def test_torch_batched_trajectories_broadcast(data: np.ndarray) -> None:
    norm = MinMaxNormalizer.fit(data)
    x = torch.as_tensor(data[:60].reshape(3, 20, 5), dtype=torch.float32)
    y = norm.normalize(x)
    assert y.shape == (3, 20, 5)
    np.testing.assert_allclose(y.reshape(60, 5).numpy(), norm.normalize(data[:60]), rtol=1e-5, atol=1e-5)


def test_gaussian_gives_zero_mean_unit_std(data: np.ndarray) -> None:
    out = GaussianNormalizer.fit(data).normalize(data)
    np.testing.assert_allclose(out.mean(axis=0), 0.0, atol=1e-10)
    np.testing.assert_allclose(out.std(axis=0), 1.0, atol=1e-10)


@pytest.mark.parametrize("cls", [MinMaxNormalizer, GaussianNormalizer])
def test_state_dict_round_trip(cls: type[Normalizer], data: np.ndarray) -> None:
    norm = cls.fit(data)
    state = json.loads(json.dumps(norm.state_dict()))  # what a bundle stores: plain JSON
    assert state["kind"] == cls.kind
    loaded = Normalizer.from_state_dict(state)
    assert type(loaded) is cls
    probe = data[:17] * 1.5 + 0.3
    np.testing.assert_array_equal(loaded.normalize(probe), norm.normalize(probe))
    np.testing.assert_array_equal(loaded.unnormalize(probe), norm.unnormalize(probe))


@pytest.mark.parametrize("state", [{"kind": "robust", "low": [0.0]}, {"low": [0.0], "high": [1.0]}])
def test_unknown_kind_raises(state: dict) -> None:
    with pytest.raises(ValueError, match="unknown normalizer kind"):
        Normalizer.from_state_dict(state)


@pytest.mark.parametrize("cls", [MinMaxNormalizer, GaussianNormalizer])
def test_constant_dimension_stays_finite(cls: type[Normalizer], data: np.ndarray) -> None:
    data = data.copy()
    data[:, 2] = 4.25
    norm = cls.fit(data)
    out = norm.normalize(data)
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(norm.unnormalize(out)[:, 2], 4.25)
    t = norm.normalize(torch.as_tensor(data, dtype=torch.float32))
    assert torch.isfinite(t).all()
    # the other dimensions are unaffected by the degenerate one
    np.testing.assert_allclose(out[:, 1], cls.fit(data[:, [1]]).normalize(data[:, [1]])[:, 0])
