"""Training windows: episode-bounded windows, mixing datasets per batch, and episode subsets."""

from __future__ import annotations

import numpy as np
import pytest

from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.data.schema import Trajectories, make_metadata
from adaptdiffuser.data.windows import MixedWindowDataset, WindowDataset, joint_array, subset_episodes


def trajectories(lengths: list[int], offset: float) -> Trajectories:
    n = sum(lengths)
    obs = np.full((n, 4), offset, dtype=np.float32)
    obs[:, 0] += np.arange(n)
    return Trajectories(
        episode_id=np.repeat(np.arange(len(lengths)), lengths),
        step=np.concatenate([np.arange(k) for k in lengths]),
        observation=obs,
        action=np.zeros((n, 2), dtype=np.float32),
        reward=np.zeros(n, dtype=np.float32),
        terminal=np.zeros(n, dtype=bool),
        timeout=np.zeros(n, dtype=bool),
        metadata=make_metadata("maze2d-umaze", 4, 2, "expert", {}),
    )


def test_windows_stay_inside_episodes() -> None:
    traj = trajectories([10, 3, 8], 0.0)
    normalizer = MinMaxNormalizer.fit(joint_array(traj))
    data = WindowDataset(traj, 5, normalizer)
    assert len(data) == (10 - 5 + 1) + (8 - 5 + 1)  # the 3-step episode is too short
    batch = normalizer.unnormalize(data.sample(64, np.random.default_rng(0)).astype(np.float64))
    steps = np.diff(batch[:, :, 2], axis=1)  # x grows by one per row within an episode
    np.testing.assert_allclose(steps, 1.0, atol=1e-4)
    with pytest.raises(ValueError, match="horizon=20"):
        WindowDataset(traj, 20, normalizer)


def test_mixed_batches_follow_the_weights() -> None:
    expert, synthetic = trajectories([40], 0.0), trajectories([40], 100.0)
    normalizer = MinMaxNormalizer.fit(np.concatenate([joint_array(expert), joint_array(synthetic)]))
    mixed = MixedWindowDataset([WindowDataset(expert, 8, normalizer), WindowDataset(synthetic, 8, normalizer)], [1, 1])
    assert mixed.counts(32) == [16, 16] and mixed.counts(5) == [3, 2] and sum(mixed.counts(7)) == 7
    batch = normalizer.unnormalize(mixed.sample(32, np.random.default_rng(0)).astype(np.float64))
    from_synthetic = batch[:, 0, 3] > 50  # the y coordinate tells the source apart
    assert from_synthetic.sum() == 16 and not from_synthetic[:16].any()
    assert MixedWindowDataset([WindowDataset(expert, 8, normalizer)] * 2, [3, 1]).counts(32) == [24, 8]
    with pytest.raises(ValueError, match="weights"):
        MixedWindowDataset([WindowDataset(expert, 8, normalizer)], [0.0])


def test_subset_episodes_keeps_whole_episodes() -> None:
    traj = trajectories([5] * 10, 0.0)
    half = subset_episodes(traj, 0.5, np.random.default_rng(0))
    assert len(half.episodes()) == 5 and len(half) == 25
    assert all(np.array_equal(half.step[ep], np.arange(5)) for ep in half.episodes())
    assert len(subset_episodes(traj, 0.01, np.random.default_rng(0)).episodes()) == 1
    assert subset_episodes(traj, 1.0, np.random.default_rng(0)) is traj
    with pytest.raises(ValueError, match="fraction"):
        subset_episodes(traj, 0.0, np.random.default_rng(0))
