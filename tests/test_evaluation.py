"""The evaluation protocol: normalized scores, fixed-seed lock-step episodes on real U-Maze, summaries."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import maze_sim

from adaptdiffuser.contract import EpisodeBatchResult
from adaptdiffuser.evaluation import RandomController, episode_rng, normalized_score, run_episodes, summarize
from adaptdiffuser.families.maze2d.expert import ExpertController
from adaptdiffuser.family_registry import get_family


def umaze_factory():
    return maze_sim()


def run(controller_cls, seed: int = 5, n: int = 4, batch_size: int = 2) -> EpisodeBatchResult:
    return run_episodes(umaze_factory, controller_cls(seed), n, seed=seed, batch_size=batch_size, progress=False)


def test_normalized_score_reference_points_and_linearity() -> None:
    assert normalized_score(10.0, 10.0, 60.0) == pytest.approx(0.0)
    assert normalized_score(60.0, 10.0, 60.0) == pytest.approx(100.0)
    assert normalized_score(22.5, 10.0, 60.0) == pytest.approx(25.0)
    assert normalized_score(110.0, 10.0, 60.0) == pytest.approx(200.0)
    np.testing.assert_allclose(normalized_score(np.array([0.0, 5.0, 10.0]), -10.0, 10.0), [50.0, 75.0, 100.0])


@pytest.mark.parametrize(("r_min", "r_max"), [(5.0, 5.0), (10.0, 2.0)])
def test_normalized_score_rejects_bad_references(r_min: float, r_max: float) -> None:
    with pytest.raises(ValueError, match="R_max > R_min"):
        normalized_score(1.0, r_min, r_max)


def test_episode_rng_is_per_seed_and_episode() -> None:
    assert episode_rng(3, 1).integers(1 << 30) == episode_rng(3, 1).integers(1 << 30)
    assert episode_rng(3, 1).integers(1 << 30) != episode_rng(3, 2).integers(1 << 30)
    assert episode_rng(3, 1).integers(1 << 30) != episode_rng(4, 1).integers(1 << 30)


def test_run_episodes_random_and_expert() -> None:
    random_a, random_b = run(RandomController), run(RandomController)
    expert_a, expert_b = run(ExpertController), run(ExpertController)

    for result in (random_a, expert_a):
        assert result.episodes == [0, 1, 2, 3]
        assert len(result.returns) == len(result.final_success) == len(result.first_goal_step) == 4
        assert all(ex.shape == (301, 4) for ex in result.executed)
        assert result.plans == [None] * 4
        for ret, first, ex, start in zip(
            result.returns, result.first_goal_step, result.executed, result.starts, strict=True
        ):
            assert 0.0 <= ret <= 300.0 and float(ret).is_integer()
            assert (first >= 0) == (ret > 0)
            np.testing.assert_array_equal(ex[0], start)

    # the same seed gives the same episodes
    assert random_a.returns == random_b.returns and expert_a.returns == expert_b.returns
    for x, y in zip(expert_a.executed, expert_b.executed, strict=True):
        np.testing.assert_array_equal(x, y)
    # both controllers start from the same protocol states
    for x, y in zip(random_a.starts, expert_a.starts, strict=True):
        np.testing.assert_array_equal(x, y)
    assert len({tuple(s) for s in expert_a.starts}) == 4

    for goal in expert_a.goals:  # the fixed evaluation goal, U-Maze cell (1, 1), with zero velocity
        np.testing.assert_array_equal(goal, [-1.0, 1.0, 0.0, 0.0])
    assert all(expert_a.final_success) and min(expert_a.first_goal_step) >= 0
    assert np.mean(expert_a.returns) > 150.0
    assert np.mean(expert_a.returns) > np.mean(random_a.returns) + 100.0


def test_results_do_not_depend_on_batch_size_and_seed_matters() -> None:
    in_pairs = run(ExpertController, n=3, batch_size=2)
    all_at_once = run(ExpertController, n=3, batch_size=3)
    one_by_one = run(RandomController, n=3, batch_size=1)
    assert in_pairs.returns == all_at_once.returns
    for x, y in zip(in_pairs.executed, all_at_once.executed, strict=True):
        np.testing.assert_array_equal(x, y)
    assert run(RandomController, n=3, batch_size=3).returns == one_by_one.returns
    other_seed = run(ExpertController, seed=6, n=3, batch_size=3)
    assert not np.array_equal(other_seed.starts[0], in_pairs.starts[0])


def test_summarize_hand_built_result() -> None:
    result = EpisodeBatchResult(
        episodes=[0, 1, 2, 3],
        returns=[0.0, 50.0, 100.0, 150.0],
        final_success=[False, True, True, True],
        first_goal_step=[-1, 200, 100, 20],
    )
    summary = summarize(result, r_min=0.0, r_max=200.0)
    assert set(summary) == {"score_mean", "score_stderr", "return_mean", "n_episodes"}
    assert summary["score_mean"] == pytest.approx(37.5)
    scores = np.array([0.0, 25.0, 50.0, 75.0])
    expected_stderr = math.sqrt(((scores - 37.5) ** 2).sum() / 3) / 2
    assert summary["score_stderr"] == pytest.approx(expected_stderr)
    assert summary["return_mean"] == pytest.approx(75.0)
    assert summary["n_episodes"] == 4 and isinstance(summary["n_episodes"], int)
    assert all(isinstance(summary[k], float) for k in ("score_mean", "score_stderr", "return_mean"))
    # the success rate is the maze family's own metric, added beside the score metrics by the evaluate stage
    maze = get_family("maze2d").episode_metrics(result)
    assert maze == {"success_rate": pytest.approx(0.75)} and isinstance(maze["success_rate"], float)


def test_summarize_single_episode_has_zero_stderr() -> None:
    result = EpisodeBatchResult(episodes=[0], returns=[30.0], final_success=[False], first_goal_step=[-1])
    summary = summarize(result, r_min=10.0, r_max=50.0)
    assert summary == {
        "score_mean": pytest.approx(50.0),
        "score_stderr": 0.0,
        "return_mean": 30.0,
        "n_episodes": 1,
    }
    assert get_family("maze2d").episode_metrics(result) == {"success_rate": 0.0}
