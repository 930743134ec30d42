"""Per-dimension normalizers, fitted on expert data and saved with each model so all phases share units."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import numpy as np
import torch

ArrayLike = np.ndarray | torch.Tensor


class Normalizer(ABC):
    """Maps raw vectors to the model's units and back, dimension by dimension."""

    kind: str

    @abstractmethod
    def normalize(self, x: ArrayLike) -> ArrayLike: ...

    @abstractmethod
    def unnormalize(self, x: ArrayLike) -> ArrayLike: ...

    @abstractmethod
    def state_dict(self) -> dict[str, Any]: ...

    @staticmethod
    def from_state_dict(state: dict[str, Any]) -> Normalizer:
        """Rebuild a saved normalizer."""
        kinds = {cls.kind: cls for cls in (MinMaxNormalizer, GaussianNormalizer)}
        if state.get("kind") not in kinds:
            raise ValueError(f"unknown normalizer kind {state.get('kind')!r}")
        return kinds[state["kind"]]._load(state)


def _like(values: np.ndarray, x: ArrayLike) -> ArrayLike:
    if isinstance(x, torch.Tensor):
        return torch.as_tensor(values, dtype=x.dtype, device=x.device)
    return values


class MinMaxNormalizer(Normalizer):
    """Scale each dimension's [min, max] to [-1, 1] (Diffuser's Maze2D choice)."""

    kind = "minmax"

    def __init__(self, low: np.ndarray, high: np.ndarray) -> None:
        self.low = np.asarray(low, dtype=np.float64)
        self.high = np.asarray(high, dtype=np.float64)
        self.span = np.maximum(self.high - self.low, 1e-6)

    @classmethod
    def fit(cls, x: np.ndarray) -> MinMaxNormalizer:
        return cls(x.min(axis=0), x.max(axis=0))

    def normalize(self, x: ArrayLike) -> ArrayLike:
        return 2.0 * (x - _like(self.low, x)) / _like(self.span, x) - 1.0

    def unnormalize(self, x: ArrayLike) -> ArrayLike:
        return (x + 1.0) / 2.0 * _like(self.span, x) + _like(self.low, x)

    def state_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "low": self.low.tolist(), "high": self.high.tolist()}

    @classmethod
    def _load(cls, state: dict[str, Any]) -> MinMaxNormalizer:
        return cls(np.array(state["low"]), np.array(state["high"]))


class GaussianNormalizer(Normalizer):
    """Standardise each dimension to zero mean, unit variance (Diffuser's locomotion choice)."""

    kind = "gaussian"

    def __init__(self, mean: np.ndarray, std: np.ndarray) -> None:
        self.mean = np.asarray(mean, dtype=np.float64)
        self.std = np.maximum(np.asarray(std, dtype=np.float64), 1e-6)

    @classmethod
    def fit(cls, x: np.ndarray) -> GaussianNormalizer:
        return cls(x.mean(axis=0), x.std(axis=0))

    def normalize(self, x: ArrayLike) -> ArrayLike:
        return (x - _like(self.mean, x)) / _like(self.std, x)

    def unnormalize(self, x: ArrayLike) -> ArrayLike:
        return x * _like(self.std, x) + _like(self.mean, x)

    def state_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "mean": self.mean.tolist(), "std": self.std.tolist()}

    @classmethod
    def _load(cls, state: dict[str, Any]) -> GaussianNormalizer:
        return cls(np.array(state["mean"]), np.array(state["std"]))


def fit_normalizer(kind: str, x: np.ndarray) -> Normalizer:
    """A normalizer of ``kind`` (``minmax`` or ``gaussian``) fitted to the rows of ``x``."""
    kinds = {cls.kind: cls for cls in (MinMaxNormalizer, GaussianNormalizer)}
    if kind not in kinds:
        raise ValueError(f"unknown normalizer kind {kind!r}; choose one of {sorted(kinds)}")
    return kinds[kind].fit(x)
