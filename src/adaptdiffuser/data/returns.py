"""Value targets for Diffuser's value guidance: discounted returns-to-go, and windows paired with them.

The return-to-go of step ``i`` of an episode is ``G_i = sum_{j >= i, j in episode} discount^(j - i) r_j``; it
never crosses an episode boundary. As Diffuser does, a step marked ``terminal`` (a real termination, not a
time-out) has ``terminal_penalty`` added to its reward. A time-out simply ends the sum (no bootstrap).
"""

from __future__ import annotations

import numpy as np

from adaptdiffuser.data.normalizer import Normalizer
from adaptdiffuser.data.schema import Trajectories
from adaptdiffuser.data.windows import joint_array


def returns_to_go(traj: Trajectories, discount: float = 0.997, terminal_penalty: float = -100.0) -> np.ndarray:
    """Per-step discounted return-to-go ``[len(traj)]`` (float64) within each episode of ``traj``."""
    if not 0.0 < discount <= 1.0:
        raise ValueError(f"discount must be in (0, 1], got {discount}")
    rewards = (traj.reward.astype(np.float64) + terminal_penalty * traj.terminal.astype(np.float64)).tolist()
    out = [0.0] * len(rewards)
    for ep in traj.episodes():
        acc = 0.0
        for i in range(ep.stop - 1, ep.start - 1, -1):  # G_i = r_i + discount * G_{i+1}
            acc = rewards[i] + discount * acc
            out[i] = acc
    return np.asarray(out, dtype=np.float64)


class ValueWindowDataset:
    """Normalized windows ``[horizon, act_dim + obs_dim]`` (the :class:`~adaptdiffuser.data.windows.WindowDataset`
    layout) paired with the return-to-go of each window's first step.

    With ``pad`` (the default, as Diffuser's ``use_padding``), a window may start at any step of an episode, and
    rows past the episode's end repeat its last row (Diffuser pads with zeros instead; repeating keeps the padded
    rows on the data manifold), so every step is a training target and episodes shorter than the horizon are used.
    Without ``pad``, only windows fully inside an episode are used (shorter episodes are skipped).
    """

    def __init__(
        self,
        traj: Trajectories,
        horizon: int,
        normalizer: Normalizer,
        discount: float = 0.997,
        terminal_penalty: float = -100.0,
        pad: bool = True,
    ) -> None:
        if horizon <= 0:
            raise ValueError(f"horizon must be positive, got {horizon}")
        self.horizon = horizon
        self.act_dim = traj.metadata["act_dim"]
        self.data = normalizer.normalize(joint_array(traj).astype(np.float64)).astype(np.float32)
        self.returns = returns_to_go(traj, discount, terminal_penalty).astype(np.float32)
        starts, lasts = [], []
        for ep in traj.episodes():
            stop = ep.stop if pad else ep.stop - horizon + 1
            if stop > ep.start:
                starts.append(np.arange(ep.start, stop))
                lasts.append(np.full(stop - ep.start, ep.stop - 1))
        if not starts:
            raise ValueError(f"no episode is at least horizon={horizon} steps long and pad is off")
        self.starts = np.concatenate(starts)
        self.lasts = np.concatenate(lasts)

    def __len__(self) -> int:
        return len(self.starts)

    def sample(self, batch_size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """A batch of normalized windows ``[batch, horizon, transition]`` and their values ``[batch]`` (float32)."""
        pick = rng.integers(len(self.starts), size=batch_size)
        starts = self.starts[pick]
        rows = np.minimum(starts[:, None] + np.arange(self.horizon)[None, :], self.lasts[pick][:, None])
        return self.data[rows], self.returns[starts]
