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
