"""Per-row noise for samplers, counter-based: the noise a row gets is a pure function of the row's seed, the index
of the draw (initial noise, then one per denoising step) and the element's position, computed for the whole batch
in one vectorized pass. So a row's noise never depends on which other rows share its batch or where it sits in it,
and a batch of thousands of rows costs a dozen tensor operations per draw instead of one generator call per row
(one kernel launch each on a GPU).

The integers are SplitMix64's (Steele, Lea and Flood, 2014): word ``n`` of a stream keyed ``k`` is
``mix64(k + n * gamma)``, a counter-based generator by construction, evaluated here on int64 tensors (their
multiplication wraps modulo 2**64, which is what the mixer needs). Each 64-bit word gives two normals by the
Box-Muller transform of two 24-bit uniforms."""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import torch

_U64 = 1 << 64


def _signed(value: int) -> int:
    """A 64-bit unsigned constant as the int64 with the same bits."""
    return value - _U64 if value >= 1 << 63 else value


_GAMMA = _signed(0x9E3779B97F4A7C15)  # SplitMix64's increment (the golden ratio's 64 fractional bits)
_MIX1 = _signed(0xBF58476D1CE4E5B9)
_MIX2 = _signed(0x94D049BB133111EB)


def _shift_right(z: torch.Tensor, bits: int) -> torch.Tensor:
    """Logical right shift of int64 words (torch shifts arithmetically: the sign bits are masked off)."""
    return (z >> bits).bitwise_and_((1 << (64 - bits)) - 1)


def mix64(z: torch.Tensor) -> torch.Tensor:
    """SplitMix64's output function on int64 tensors: a bijection of 64-bit words that scrambles every bit."""
    z = z ^ _shift_right(z, 30)
    z.mul_(_MIX1)
    z.bitwise_xor_(_shift_right(z, 27)).mul_(_MIX2)
    return z.bitwise_xor_(_shift_right(z, 31))


def stream_words(keys: torch.Tensor, count: int) -> torch.Tensor:
    """Words ``1..count`` of the SplitMix64 streams keyed by ``keys`` (int64 ``[rows, 1]``): ``[rows, count]``."""
    counters = torch.arange(1, count + 1, dtype=torch.int64, device=keys.device)
    return mix64(counters.mul_(_GAMMA).add(keys))


class RowNoise:
    """Standard normal noise of ``dtype`` for a batch of ``len(seeds)`` rows on ``device``. Draw ``d`` (the
    ``d``-th call of :meth:`randn`) of row ``i`` reads the SplitMix64 stream keyed by ``mix64(mix64(seeds[i]) ^ d)``
    from its first word on: the same numbers alone or in any batch. The transform runs in float64 for float64
    noise and in float32 otherwise."""

    def __init__(
        self,
        seeds: Iterable[int] | np.ndarray,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        values = np.asarray(seeds if isinstance(seeds, np.ndarray) else list(seeds))
        if values.ndim != 1 or len(values) == 0:
            raise ValueError(f"need a non-empty flat sequence of seeds, one per row; got shape {values.shape}")
        if not np.issubdtype(values.dtype, np.integer) or (values < 0).any():
            raise ValueError(f"seeds must be non-negative integers, got {values.tolist()}")
        self.seeds = [int(s) for s in values]
        if max(self.seeds) >= _U64:
            raise ValueError(f"seeds must be below 2**64, got {max(self.seeds)}")
        self.device = torch.device(device)
        self.dtype = dtype
        raw = torch.tensor([_signed(s) for s in self.seeds], dtype=torch.int64, device=self.device)
        self._row_keys = mix64(raw).unsqueeze(1)  # [rows, 1]
        self.draws = 0

    def __len__(self) -> int:
        return len(self.seeds)

    def randn(self, shape: tuple[int, ...] | list[int] | torch.Size) -> torch.Tensor:
        """Noise ``[rows, *shape]``: row ``i``'s next draw, a function of its seed, the draw's index and the
        element's position only."""
        shape = tuple(shape)
        size = math.prod(shape)
        keys = mix64(self._row_keys ^ self.draws)
        self.draws += 1
        words = stream_words(keys, (size + 1) // 2)
        work = torch.float64 if self.dtype == torch.float64 else torch.float32
        # two 24-bit uniforms per word: u1 in (0, 1] (its log is finite), u2 in [0, 1); exact in float32
        u1 = _shift_right(words, 40).add_(1).to(work).mul_(2.0**-24)
        u2 = (words >> 8).bitwise_and_(0xFFFFFF).to(work).mul_(2.0**-24)
        radius = u1.log_().mul_(-2.0).sqrt_()
        angle = u2.mul_(2.0 * math.pi)
        normals = torch.cat([angle.cos().mul_(radius), angle.sin_().mul_(radius)], dim=1)[:, :size]
        return normals.to(self.dtype).reshape(len(self), *shape)
