"""The gold-coin task: the fixed evaluation cases (which kinds each maze allows, the paper's Medium case,
reproducibility) and the scoring of executed episodes (the order of coin and goal decides ``both``)."""

from __future__ import annotations

import numpy as np
import pytest

from adaptdiffuser.cli import _figures
from adaptdiffuser.contract import Controller
from adaptdiffuser.evaluation import run_episodes
from adaptdiffuser.families.maze2d.gold_coin import (
    PAPER_MEDIUM_CASE,
    coin_cases,
    coin_kind,
    coin_outcome,
    summarize_coin,
)
from adaptdiffuser.families.maze2d.simulator import Maze2D, resolve_layout


def _maze(name: str) -> Maze2D:
    return Maze2D(resolve_layout(name), name=name)


def test_medium_cases_cover_every_kind_and_include_the_papers_case() -> None:
    env = _maze("medium")
    cases = coin_cases(env, per_kind=3, rng=np.random.default_rng(0))
    assert len(cases) == 3 * 3 + 1
    assert set(cases.kinds) == {"on_path", "off_path", "behind_start"}
    start, coin = PAPER_MEDIUM_CASE["start"], PAPER_MEDIUM_CASE["coin"]
    assert (cases.start_cells[-1], cases.coin_cells[-1]) == (start, coin)
    assert cases.kinds[-1] == coin_kind(env, start, coin) == "off_path"  # a detour away from the shortest path
    np.testing.assert_allclose(cases.coins[-1], env.cell_to_xy(coin))
    for kind, s, c in zip(cases.kinds, cases.start_cells, cases.coin_cells, strict=True):
        assert coin_kind(env, s, c) == kind


def test_umaze_has_no_off_path_case_and_the_same_seed_gives_the_same_cases() -> None:
    env = _maze("umaze")
    first = coin_cases(env, per_kind=4, rng=np.random.default_rng(3))
    again = coin_cases(env, per_kind=4, rng=np.random.default_rng(3))
    assert set(first.kinds) == {"on_path", "behind_start"}
    np.testing.assert_array_equal(first.starts, again.starts)
    assert first.coin_cells == again.coin_cells


def test_non_positive_cases_per_kind_is_rejected() -> None:
    with pytest.raises(ValueError, match="cases per kind must be positive"):
        coin_cases(_maze("umaze"), per_kind=0, rng=np.random.default_rng(0))


# U-Maze (cells are 1 apart, y up): the goal is the top-left cell, the corridor runs right, down and back left
GOAL = np.array([-1.0, 1.0])
COIN = np.array([1.0, -1.0])  # the bottom-right cell
FAR = np.array([0.0, 1.0])  # top corridor: 1 from the goal, 2.2 from the coin
RADIUS = 0.5


def _states(*stations: tuple[np.ndarray, int]) -> np.ndarray:
    """Executed states ``[T + 1, 4]``: each station's position held for its number of steps, at rest."""
    xy = np.concatenate([np.repeat(p[None], n, axis=0) for p, n in stations])
    return np.concatenate([xy, np.zeros_like(xy)], axis=1)


NEAR_COIN, NEAR_GOAL = COIN + [0.3, 0.2], GOAL + [0.2, -0.3]  # inside the radii
CLOSE_MISS = COIN + [0.0, 0.55]  # 0.55 from the coin: not a pick


@pytest.mark.parametrize(
    ("stations", "expected"),
    [
        # (positions held, steps) -> (pick_step, goal_after_pick_step, goal_step)
        ([(FAR, 3), (NEAR_COIN, 2), (FAR, 4), (NEAR_GOAL, 3)], (3, 9, 9)),  # coin, then goal
        ([(FAR, 2), (NEAR_GOAL, 3), (FAR, 2), (NEAR_COIN, 4)], (7, -1, 2)),  # goal, then coin: not both
        ([(NEAR_GOAL, 1), (FAR, 3), (NEAR_COIN, 1), (FAR, 2), (NEAR_GOAL, 2)], (4, 7, 0)),  # goal, coin, goal again
        ([(FAR, 2), (CLOSE_MISS, 3), (NEAR_GOAL, 2)], (-1, -1, 5)),  # passes the coin just outside its radius
        ([(FAR, 2), (NEAR_COIN, 5)], (2, -1, -1)),  # coin, never the goal
    ],
    ids=["coin-goal", "goal-coin", "goal-coin-goal", "near-miss", "coin-only"],
)
def test_coin_outcome_follows_the_order_of_events(
    stations: list[tuple[np.ndarray, int]], expected: tuple[int, int, int]
) -> None:
    env = _maze("umaze")
    np.testing.assert_allclose(env.goal_xy, GOAL)
    plan = _states((FAR, 4))  # a plan inside the corridor
    outcome = coin_outcome(env, _states(*stations), COIN, RADIUS, plan)
    assert (outcome.pick_step, outcome.goal_after_pick_step, outcome.goal_step) == expected
    assert outcome.picked == (expected[0] >= 0)
    assert outcome.both == (expected[1] >= 0)  # both means the goal was reached after the coin, not just both seen
    assert not outcome.plan_collides
    # a plan through the wall between the corridors collides
    through_wall = _states((FAR, 1), (np.array([0.0, 0.0]), 1), (COIN, 1))
    assert coin_outcome(env, _states(*stations), COIN, RADIUS, through_wall).plan_collides


def test_summary_counts_only_coin_then_goal_as_both() -> None:
    env = _maze("umaze")
    plan = _states((FAR, 4))
    episodes = [
        _states((FAR, 3), (NEAR_COIN, 2), (FAR, 4), (NEAR_GOAL, 3)),  # both, at step 9
        _states((FAR, 2), (NEAR_GOAL, 3), (FAR, 2), (NEAR_COIN, 4)),  # goal then coin
        _states((NEAR_GOAL, 1), (FAR, 3), (NEAR_COIN, 1), (FAR, 2), (NEAR_GOAL, 2)),  # both, at step 7
        _states((FAR, 2), (NEAR_GOAL, 2)),  # goal only
    ]
    outcomes = [coin_outcome(env, ex, COIN, RADIUS, plan) for ex in episodes]
    kinds = ["on_path", "behind_start", "behind_start", "on_path"]
    summary = summarize_coin(outcomes, kinds, np.array([10.0, 20.0, 30.0, 40.0]))
    assert summary["pick_rate"] == pytest.approx(3 / 4)
    assert summary["goal_rate"] == pytest.approx(1.0)
    assert summary["both_rate"] == pytest.approx(2 / 4)
    assert summary["steps_to_goal_mean"] == pytest.approx((9 + 7) / 2)  # steps to the goal after the pick
    assert summary["both_rate_on_path"] == pytest.approx(1 / 2)
    assert summary["both_rate_behind_start"] == pytest.approx(1 / 2)
    assert summary["collision_rate"] == 0.0 and summary["n_episodes"] == 4
    assert summary["score_mean"] == pytest.approx(25.0)
    assert summary["score_stderr"] == pytest.approx(np.std([10.0, 20.0, 30.0, 40.0], ddof=1) / 2)
    # no case that reaches both: its steps are not measured (None), not a number a mean over seeds would take in
    none = summarize_coin(outcomes[1::2], kinds[1::2], np.array([20.0, 40.0]))
    assert none["both_rate"] == 0.0 and none["steps_to_goal_mean"] is None
    line = _figures(sorted(none.items()))  # the evaluate-unseen stage's closing line prints it, and does not fail
    assert "steps_to_goal_mean none" in line and "both_rate 0," in line


class WaypointController(Controller):
    """Drives each episode through its own list of positions with D4RL's expert PD law, then holds the last."""

    def __init__(self, routes: list[list[np.ndarray]]) -> None:
        self.routes = routes

    def begin(self, envs, obs, episodes):
        self.todo = [list(self.routes[e]) for e in episodes]

    def act(self, envs, obs, t):
        actions = []
        for todo, o in zip(self.todo, obs, strict=True):
            if len(todo) > 1 and np.linalg.norm(todo[0] - o[:2]) < 0.2:
                todo.pop(0)
            actions.append(np.clip(10.0 * (todo[0] - o[:2]) - o[2:4], -1.0, 1.0))
        return np.stack(actions)


def test_real_episodes_record_the_order_of_coin_and_goal() -> None:
    """In the real simulator, as the stage scores them: executed states from ``run_episodes`` -> outcomes."""
    env = _maze("umaze")
    right, bottom = np.array([1.0, 1.0]), COIN
    start = np.array([0.0, 1.0, 0.0, 0.0])
    routes = [
        [right, bottom, right, GOAL],  # fetch the coin behind the start, then the goal
        [GOAL, right, bottom],  # the goal first, then the coin, and stay there
    ]
    result = run_episodes(
        lambda: _maze("umaze"),
        WaypointController(routes),
        2,
        seed=0,
        batch_size=2,
        progress=False,
        reset=lambda e, i: e.set_state(start),
    )
    plan = _states((FAR, 4))
    first, second = (coin_outcome(env, ex, COIN, RADIUS, plan) for ex in result.executed)
    assert 0 < first.pick_step < first.goal_after_pick_step == first.goal_step and first.both
    assert 0 < second.goal_step < second.pick_step and second.picked and not second.both
    assert second.goal_after_pick_step == -1
