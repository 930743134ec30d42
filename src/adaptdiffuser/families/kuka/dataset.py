"""KUKA datasets: episodes of states only (the schema's ``act_dim`` 0), as one :class:`Trajectories`."""

from __future__ import annotations

from typing import Any

import numpy as np

from adaptdiffuser.data.schema import Trajectories, make_metadata
from adaptdiffuser.families.kuka.scene import OBS_DIM


def state_episodes(
    observations: list[np.ndarray],
    env: str,
    source: str,
    generator: dict[str, Any],
    rewards: list[np.ndarray] | None = None,
    per_episode: dict[str, np.ndarray] | None = None,
) -> Trajectories:
    """Episodes ``[T_i, 39]`` in order (ids 0..n-1, the last row of each a timeout), with their per-step rewards
    (zeros when not given) and columns holding one value per episode (``per_episode``, repeated on its rows)."""
    lengths = [len(o) for o in observations]
    n = sum(lengths)
    return Trajectories(
        episode_id=np.repeat(np.arange(len(observations)), lengths),
        step=np.concatenate([np.arange(k) for k in lengths]),
        observation=np.concatenate(observations).astype(np.float32),
        action=np.zeros((n, 0), dtype=np.float32),
        reward=np.zeros(n, np.float32) if rewards is None else np.concatenate(rewards).astype(np.float32),
        terminal=np.zeros(n, dtype=bool),
        timeout=np.concatenate([np.arange(k) == k - 1 for k in lengths]),
        metadata=make_metadata(env, OBS_DIM, 0, source, generator),
        extra={name: np.repeat(np.asarray(values), lengths, axis=0) for name, values in (per_episode or {}).items()},
    )
