"""Per-row noise for samplers: every row of a batch owns a generator seeded by its own integer, so the noise a row
gets (initial and per-step) never depends on which other rows share its batch or where it sits in it."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch


class RowNoise:
    """Standard normal noise of ``dtype`` for a batch of ``len(seeds)`` rows on ``device``: row ``i`` draws from its
    own ``torch.Generator(device).manual_seed(seeds[i])``, so its draws are the same alone or in any batch."""

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
        self.device = torch.device(device)
        self.dtype = dtype
        self.generators = [torch.Generator(device=self.device).manual_seed(s) for s in self.seeds]

    def __len__(self) -> int:
        return len(self.generators)

    def randn(self, shape: tuple[int, ...] | list[int] | torch.Size) -> torch.Tensor:
        """Noise ``[rows, *shape]``: row ``i`` is the next ``shape`` draw of row ``i``'s generator."""
        shape = tuple(shape)
        return torch.stack(
            [torch.randn(shape, device=self.device, dtype=self.dtype, generator=g) for g in self.generators]
        )
