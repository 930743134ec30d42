"""Training windows: fixed-length slices of episodes as [action, observation] rows, normalized."""

from __future__ import annotations

import numpy as np

from adaptdiffuser.data.normalizer import Normalizer
from adaptdiffuser.data.schema import Trajectories


def joint_array(traj: Trajectories) -> np.ndarray:
    """Rows of ``[action, observation]``, the layout the diffusion model works on."""
    return np.concatenate([traj.action, traj.observation], axis=1).astype(np.float32)


class WindowDataset:
    """All length-``horizon`` windows that lie inside one episode; sampled uniformly at random."""

    def __init__(self, traj: Trajectories, horizon: int, normalizer: Normalizer) -> None:
        self.horizon = horizon
        self.act_dim = traj.metadata["act_dim"]
        self.data = normalizer.normalize(joint_array(traj).astype(np.float64)).astype(np.float32)
        starts = [np.arange(ep.start, ep.stop - horizon + 1) for ep in traj.episodes() if ep.stop - ep.start >= horizon]
        if not starts:
            raise ValueError(f"no episode is at least horizon={horizon} steps long; collect more data")
        self.starts = np.concatenate(starts)

    def __len__(self) -> int:
        return len(self.starts)

    def sample(self, batch_size: int, rng: np.random.Generator) -> np.ndarray:
        """A batch ``[batch, horizon, act_dim + obs_dim]`` of normalized windows."""
        starts = self.starts[rng.integers(len(self.starts), size=batch_size)]
        return self.data[starts[:, None] + np.arange(self.horizon)[None, :]]


class MixedWindowDataset:
    """Batches drawn from several window datasets in fixed proportions (AdaptDiffuser fine-tuning mixes expert
    and selected synthetic windows; the released code uses half and half per batch)."""

    def __init__(self, parts: list[WindowDataset], weights: list[float]) -> None:
        if not parts or len(parts) != len(weights):
            raise ValueError("need one weight per dataset and at least one dataset")
        if any(w < 0 for w in weights) or sum(weights) <= 0:
            raise ValueError(f"mixing weights must be non-negative with a positive sum, got {weights}")
        if len({p.horizon for p in parts}) != 1:
            raise ValueError("all mixed datasets must share one horizon")
        self.parts = parts
        self.weights = np.asarray(weights, dtype=np.float64) / np.sum(weights)
        self.horizon = parts[0].horizon

    def __len__(self) -> int:
        return sum(len(p) for p in self.parts)

    def counts(self, batch_size: int, rng: np.random.Generator | None = None) -> list[int]:
        """How many windows of a batch each dataset supplies: its share of ``batch_size`` rounded down or up,
        summing to ``batch_size``. Without ``rng``, by largest remainder (always the same datasets round up); with
        ``rng``, by systematic rounding at a random offset, so that over many batches each dataset supplies exactly
        its share on average (no draw is made when every share is a whole number of windows)."""
        raw = self.weights * batch_size
        if rng is not None and not np.allclose(raw, np.round(raw), rtol=0.0, atol=1e-9):
            edges = np.floor(np.cumsum(raw) + rng.random()).astype(int)
            edges[-1] = batch_size
            return np.diff(edges, prepend=0).tolist()
        counts = np.floor(raw).astype(int)
        for i in np.argsort(-(raw - counts), kind="stable")[: batch_size - counts.sum()]:
            counts[i] += 1
        return counts.tolist()

    def sample(self, batch_size: int, rng: np.random.Generator) -> np.ndarray:
        """A batch with each dataset's share of windows (see :meth:`counts`), in dataset order."""
        chunks = [p.sample(k, rng) for p, k in zip(self.parts, self.counts(batch_size, rng), strict=True) if k]
        return np.concatenate(chunks)


def subset_episodes(traj: Trajectories, fraction: float, rng: np.random.Generator) -> Trajectories:
    """A random ``fraction`` of the episodes (at least one), for the paper's limited-expert-data ablation."""
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"fraction of episodes must be in (0, 1], got {fraction}")
    episodes = traj.episodes()
    if fraction == 1.0:
        return traj
    chosen = np.sort(rng.choice(len(episodes), size=max(1, round(fraction * len(episodes))), replace=False))
    return take_episodes(traj, chosen)


def take_episodes(traj: Trajectories, indices: np.ndarray | list[int]) -> Trajectories:
    """The episodes of ``traj`` at positions ``indices`` (in :meth:`Trajectories.episodes` order), in that order."""
    episodes = traj.episodes()
    rows = np.concatenate([np.zeros(0, np.int64), *(np.arange(episodes[i].start, episodes[i].stop) for i in indices)])
    return Trajectories(
        episode_id=traj.episode_id[rows],
        step=traj.step[rows],
        observation=traj.observation[rows],
        action=traj.action[rows],
        reward=traj.reward[rows],
        terminal=traj.terminal[rows],
        timeout=traj.timeout[rows],
        metadata=traj.metadata,
        extra={name: values[rows] for name, values in traj.extra.items()},
        sim_state=None if traj.sim_state is None else traj.sim_state[rows],
    )
