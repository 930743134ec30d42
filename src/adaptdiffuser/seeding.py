"""Derived seeds: one integer seed from a params seed and the indices of what it is for (phase, task, episode,
step, sample), never from a batch position, so results do not depend on how work is batched."""

from __future__ import annotations

import numpy as np


def derive_seed(*parts: int) -> int:
    """A 32-bit seed determined by ``parts`` alone (independent of anything else that runs)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1)[0])
