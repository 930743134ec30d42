"""D4RL score reference: the random and expert returns of each locomotion environment, and the normalized score."""

from __future__ import annotations

import numpy as np

#: ``robot -> (random return, expert return)``, the constants D4RL normalizes with
REFERENCE_RETURNS: dict[str, tuple[float, float]] = {
    "hopper": (-20.272305, 3234.3),
    "walker2d": (1.629008, 4592.3),
    "halfcheetah": (-280.178953, 12135.0),
}


def robot_of(env_id: str) -> str:
    """``Hopper-v5`` (or ``hopper-medium``) -> ``hopper``; ``ValueError`` for an unknown robot."""
    robot = env_id.split("-")[0].lower()
    if robot not in REFERENCE_RETURNS:
        raise ValueError(f"no D4RL reference returns for {env_id!r}; known robots: {sorted(REFERENCE_RETURNS)}")
    return robot


def normalized_score(returns: float | np.ndarray, env_id: str) -> float | np.ndarray:
    """``100 (R - R_random) / (R_expert - R_random)`` with D4RL's reference returns of ``env_id``'s robot."""
    low, high = REFERENCE_RETURNS[robot_of(env_id)]
    score = 100.0 * (np.asarray(returns, dtype=np.float64) - low) / (high - low)
    return float(score) if score.ndim == 0 else score
