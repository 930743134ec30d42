"""Derived seeds: one integer seed from a params seed and the indices of what it is for (phase, task, episode,
step, sample), never from a batch position, so results do not depend on how work is batched."""

from __future__ import annotations

import numpy as np


def derive_seed(*parts: int) -> int:
    """A 32-bit seed determined by ``parts`` alone (independent of anything else that runs)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1)[0])


def training_seed(base: int, seed: int) -> int:
    """The seed a training-time random source uses for training seed ``seed`` (an entry of ``seeds`` in params)
    when its params seed is ``base``: ``base`` itself for training seed 0, so a one-seed run is exactly the run
    it always was, and a seed derived from both otherwise."""
    return int(base) if seed == 0 else derive_seed(base, seed, 0x5EED)
