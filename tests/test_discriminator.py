"""Evolution building blocks: tasks, generation, tracking in the real simulator, the paper's rule, selection."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import maze_sim

from adaptdiffuser.checkpoint import make_bundle
from adaptdiffuser.config import DiffusionParams, DiscriminateParams, ModelParams, Params
from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.data.schema import read_trajectories, write_trajectories
from adaptdiffuser.data.windows import WindowDataset
from adaptdiffuser.diffusion.samplers import DDIMSampler
from adaptdiffuser.evolution.discriminator import (
    QuantileRule,
    TopKRule,
    discriminate,
    generic_selection_rule,
    passes_tracking,
    planned_trajectory,
    select_by_quantile,
    select_top_k,
    track_plan,
)
from adaptdiffuser.families.maze2d.evolution import with_coin_tasks
from adaptdiffuser.families.maze2d.execution import PlanFollower
from adaptdiffuser.families.maze2d.generation import (
    NavigationTasks,
    generate_plans,
    split_task_trajectories,
    task_trajectories,
)
from adaptdiffuser.families.maze2d.selection import PAPER_MAZE_RULES
from adaptdiffuser.families.maze2d.tasks import sample_navigation_tasks
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.planning import Planner

THRESHOLD = 0.3


def expert_states(steps: int, start_cell: tuple[int, int], goal_cell: tuple[int, int]) -> np.ndarray:
    """A dynamically feasible state sequence: the expert driving from one U-Maze cell to another."""
    env = maze_sim()
    env.set_goal(goal_cell)
    obs = env.reset(np.random.default_rng(0), cell=start_cell)
    states = [obs]
    for _ in range(steps - 1):
        obs = env.step(env.expert_action(obs)).observation
        states.append(obs)
    return np.asarray(states)


def test_a_plan_through_a_wall_is_rejected() -> None:
    env = maze_sim()
    # straight down from cell (1, 1) to cell (3, 1) of U-Maze, through the wall cell (2, 1)
    y = np.linspace(1.0, -1.0, 64)
    vy = np.gradient(y) / 0.01
    plan = np.stack([np.full(64, -1.0), y, np.zeros(64), vy], axis=1)
    assert any(env.in_wall(p[:2]) for p in plan)
    tracked = track_plan(env, plan, PlanFollower)
    assert not passes_tracking(tracked, THRESHOLD)
    assert tracked.max_error > 0.5
    # the executed states never enter the wall: what would be kept is physically real
    assert not any(env.in_wall(o[:2]) for o in tracked.observations)


def test_a_plan_the_controller_can_follow_is_kept_with_its_real_states_and_actions() -> None:
    env = maze_sim()
    plan = expert_states(128, start_cell=(3, 1), goal_cell=(1, 3))
    tracked = track_plan(env, plan, PlanFollower, goal=np.array([*env.cell_to_xy((1, 3)), 0.0, 0.0]))
    assert passes_tracking(tracked, THRESHOLD), tracked.max_error
    # one action per state (the last holds the final planned position) and one reward per state
    assert tracked.observations.shape == (128, 4) and tracked.actions.shape == (128, 2)
    assert tracked.rewards.shape == (128,) and tracked.errors.shape == (127,)
    assert np.all(np.abs(tracked.actions) <= 1.0)
    # the rewards are measured against the task's goal, not the evaluation goal
    assert tracked.total_reward > 0 and tracked.steps_to_goal > 0
    np.testing.assert_array_equal(env.goal_xy, env.cell_to_xy((1, 3)))
    # replaying the kept actions from the first state reproduces the kept states exactly
    obs = env.set_state(tracked.observations[0])
    for action, expected in zip(tracked.actions[:-1], tracked.observations[1:], strict=True):
        obs = env.step(action).observation
        np.testing.assert_allclose(obs, expected)


def test_paper_rule_follows_the_appendix() -> None:
    rule = PAPER_MAZE_RULES["umaze"]
    assert rule.keeps(reward=0.0, length=201)  # long trajectories are kept
    assert not rule.keeps(reward=300.0, length=50)  # too short
    assert rule.keeps(reward=100.0, length=150)  # 100 + 150 > 210
    assert not rule.keeps(reward=50.0, length=150)  # 50 + 150 <= 210
    assert PAPER_MAZE_RULES["medium"].keeps(reward=300.0, length=300)  # 300 + 300 > 400
    assert not PAPER_MAZE_RULES["large"].keeps(reward=0.0, length=600)  # 0 + 200 <= 400


@pytest.mark.parametrize("quantile", [0.0, 0.5, 0.9, 1.0])
def test_quantile_selection_is_never_empty(quantile: float) -> None:
    rng = np.random.default_rng(0)
    for n in (1, 2, 7, 100):
        for scores in (rng.normal(size=n), np.zeros(n), np.full(n, -5.0), rng.integers(0, 3, size=n)):
            keep = select_by_quantile(scores, quantile)
            assert keep.size >= 1
            assert scores[keep].min() >= np.quantile(scores, quantile) - 1e-12
            assert np.argmax(scores) in keep or scores[keep].max() == scores.max()
    assert select_by_quantile(np.zeros(0), 0.5).size == 0
    with pytest.raises(ValueError, match="quantile"):
        select_by_quantile(np.ones(3), 1.5)


def test_top_k_selection() -> None:
    scores = np.array([0.1, 3.0, -1.0, 2.0])
    assert select_top_k(scores, 2).tolist() == [1, 3]
    assert select_top_k(scores, 10).tolist() == [1, 3, 0, 2]
    with pytest.raises(ValueError, match="k must be positive"):
        select_top_k(scores, 0)


def test_sampled_tasks_use_distinct_free_cells_and_are_reproducible() -> None:
    env = maze_sim()
    a = sample_navigation_tasks(env, 50, np.random.default_rng(3))
    b = sample_navigation_tasks(env, 50, np.random.default_rng(3))
    np.testing.assert_array_equal(a.starts, b.starts)
    assert len(a) == 50 and a.starts.shape == (50, 4) and a.goals.shape == (50, 4)
    assert np.all(np.any(a.start_cells != a.goal_cells, axis=1))
    for start, cell in zip(a.starts, a.start_cells, strict=True):
        assert env.xy_to_cell(start[:2]) == tuple(cell)
    np.testing.assert_array_equal(a.goals[:, 2:], 0.0)
    assert len({tuple(c) for c in a.goal_cells}) > 3


def test_generated_plans_hit_their_tasks_and_kept_data_round_trips(tmp_path: Path) -> None:
    env = maze_sim()
    torch.manual_seed(0)
    normalizer = MinMaxNormalizer(np.array([-1, -1, -2, -2, -5, -5.0]), np.array([1, 1, 2, 2, 5, 5.0]))
    bundle = make_bundle(ModelParams(dim=8, dim_mults=[1, 2]), DiffusionParams(horizon=16, n_steps=4), 4, 2, normalizer)
    planner = Planner(bundle, DDIMSampler(2), torch.device("cpu"))
    tasks = sample_navigation_tasks(env, 5, np.random.default_rng(1))
    plans = generate_plans(planner, tasks, batch_size=2, seed=0, progress=False)
    assert plans.shape == (5, 16, 6)
    np.testing.assert_allclose(plans[:, 0, 2:], tasks.starts, atol=1e-5)
    np.testing.assert_allclose(plans[:, -1, 2:], tasks.goals, atol=1e-5)
    np.testing.assert_array_equal(plans, generate_plans(planner, tasks, batch_size=2, seed=0, progress=False))

    tracked = [track_plan(env, p[:, 2:], PlanFollower, goal=g) for p, g in zip(plans, tasks.goals, strict=True)]
    keep = select_top_k(np.array([-t.max_error for t in tracked]), 3)
    traj = task_trajectories([tracked[i] for i in keep], tasks, keep, "maze2d-umaze", {"phase": 1})
    path = tmp_path / "selected.parquet"
    write_trajectories(path, traj)
    back = read_trajectories(path)
    assert back.metadata["source"] == "synthetic" and len(back.episodes()) == 3 and len(back) == 3 * 16
    assert sorted(set(back.extra["task_id"].tolist())) == sorted(keep.tolist())
    first = back.episodes()[0]
    np.testing.assert_allclose(back.extra["task_goal"][first][0], tasks.goals[keep[0]], atol=1e-6)
    np.testing.assert_allclose(back.observation[first], tracked[keep[0]].observations, atol=1e-6)
    np.testing.assert_allclose(back.reward[first], tracked[keep[0]].rewards)
    # a kept trajectory fills exactly one training window of the model's horizon
    assert len(WindowDataset(back, 16, normalizer)) == 3
    states, _, back_tasks = split_task_trajectories(back)
    np.testing.assert_allclose(states[1], tracked[keep[1]].observations, atol=1e-6)
    np.testing.assert_allclose(back_tasks.goals, tasks.goals[keep], atol=1e-6)
    with pytest.raises(ValueError, match="no trajectories"):
        task_trajectories([], tasks, np.zeros(0), "maze2d-umaze", {})


def _wall_and_feasible_plans() -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Three plans in U-Maze: two the expert drove (one reaching its goal early, one late) and one through a wall."""
    env = maze_sim()
    goal = np.array([*env.cell_to_xy((1, 3)), 0.0, 0.0])
    early = expert_states(128, start_cell=(1, 2), goal_cell=(1, 3))
    late = expert_states(128, start_cell=(3, 1), goal_cell=(1, 3))
    y = np.linspace(1.0, -1.0, 128)
    wall = np.stack([np.full(128, -1.0), y, np.zeros(128), np.gradient(y) / 0.01], axis=1)
    states = [early, late, wall]
    actions = [np.zeros((128, 2)) for _ in states]
    return states, actions, np.stack([goal, goal, goal])


def test_discriminate_rejects_by_tracking_then_selects_by_real_reward() -> None:
    env = maze_sim()
    states, actions, goals = _wall_and_feasible_plans()
    cfg = DiscriminateParams(max_error=THRESHOLD, rule="quantile", quantile=1.0)
    judgement = discriminate(env, states, actions, goals, cfg, QuantileRule(1.0), PlanFollower, progress=False)
    assert judgement.passed_tracking.tolist() == [True, True, False]
    assert judgement.kept.tolist() == [0]  # the one at the goal sooner scores the higher real return
    report = judgement.report()
    assert report["generated"] == 3 and report["rejected_tracking"] == 1 and report["rejected_reward"] == 1
    assert report["kept"] == 1 and report["kept_fraction"] == pytest.approx(1 / 3)
    assert report["tracking_error_mean"] > 0 and report["return_mean_kept"] >= report["return_mean"]

    # top_k keeps both feasible plans, best first; the wall plan never reaches selection
    both = discriminate(
        env,
        states,
        actions,
        goals,
        DiscriminateParams(max_error=THRESHOLD, rule="top_k", top_k=5),
        TopKRule(5),
        PlanFollower,
        progress=False,
    )
    assert both.kept.tolist() == [0, 1]


def test_discriminate_without_tracking_takes_plans_at_their_word() -> None:
    env = maze_sim()
    states, actions, goals = _wall_and_feasible_plans()
    cfg = DiscriminateParams(tracking=False, rule="top_k", top_k=3)
    judgement = discriminate(env, states, actions, goals, cfg, TopKRule(3), PlanFollower, progress=False)
    # nothing is simulated: the wall plan passes and the kept data are the planned states themselves
    assert judgement.passed_tracking.all() and len(judgement.kept) == 3
    np.testing.assert_array_equal(judgement.trajectories[2].observations, states[2])
    assert judgement.trajectories[2].max_error == 0.0
    assert (
        planned_trajectory(env, states[0], actions[0], goals[0]).total_reward == judgement.trajectories[0].total_reward
    )


def test_paper_rule_scores_length_as_the_trajectory_length() -> None:
    env = maze_sim()
    states, actions, goals = _wall_and_feasible_plans()
    rule = PAPER_MAZE_RULES["umaze"]
    judgement = discriminate(
        env,
        states,
        actions,
        goals,
        DiscriminateParams(max_error=THRESHOLD, rule="paper"),
        rule,
        PlanFollower,
        progress=False,
    )
    # with L = 128, the U-Maze rule R + (300 - L) > 210 asks for more than 38 steps at the goal
    returns = [judgement.trajectories[i].total_reward for i in (0, 1)]
    assert returns[0] > 38 >= returns[1]
    assert [rule.keeps(r, 128) for r in returns] == [True, False]
    assert judgement.kept.tolist() == [0]


def test_the_maze_family_gives_the_paper_rule_of_its_maze_and_the_generic_rules_otherwise() -> None:
    family, task = get_family("maze2d"), Params().resolve("maze2d-umaze")
    assert family.selection_rule(task, DiscriminateParams(rule="paper")) is PAPER_MAZE_RULES["umaze"]
    assert family.selection_rule(task, DiscriminateParams(rule="quantile", quantile=0.7)) == QuantileRule(0.7)
    assert family.selection_rule(task, DiscriminateParams(rule="top_k", top_k=4)) == TopKRule(4)
    with pytest.raises(ValueError, match="not a generic one"):
        generic_selection_rule(DiscriminateParams(rule="paper"))
    # every rule answers positions among the candidates, scored by real return and length
    returns, lengths = np.array([250.0, 10.0, 100.0]), np.array([128, 128, 201])
    assert PAPER_MAZE_RULES["umaze"].select(returns, lengths).tolist() == [0, 2]
    assert TopKRule(2).select(returns, lengths).tolist() == [0, 2]
    assert QuantileRule(1.0).select(returns, lengths).tolist() == [0]


def test_coin_tasks_are_kept_when_they_pick_the_coin_then_reach_the_goal() -> None:
    env = maze_sim()
    states, actions, goals = _wall_and_feasible_plans()
    coin_on_the_way = states[1][40, :2]  # passed by the late plan before it reaches the goal
    coins = np.stack([[np.nan, np.nan], coin_on_the_way, [5.0, 5.0]])
    no_cells = np.zeros((0, 2), dtype=np.int64)
    tasks = NavigationTasks(np.stack([s[0] for s in states]), goals, no_cells, no_cells, coins)
    cfg = DiscriminateParams(max_error=THRESHOLD, rule="top_k", top_k=5)
    # the generic discriminator ranks only the navigation task; the coin tasks are the family's to judge
    ranked = discriminate(env, states, actions, goals, cfg, TopKRule(5), PlanFollower, ~tasks.has_coin(), False)
    assert ranked.kept.tolist() == [0] and "coin_kept" not in ranked.report()
    judgement = with_coin_tasks(ranked, tasks, radius=0.5, must_end_at_goal=False)
    assert judgement.kept.tolist() == [0, 1]  # the wall plan failed tracking, whatever its coin
    assert judgement.report()["coin_generated"] == 2 and judgement.report()["coin_kept"] == 1
    far = with_coin_tasks(ranked, tasks, radius=0.01, must_end_at_goal=False)  # the coin missed by more
    assert far.kept.tolist() == [0] and far.report()["coin_kept"] == 0
    with pytest.raises(ValueError, match="ranked marks 2 plans"):
        discriminate(env, states, actions, goals, cfg, TopKRule(5), PlanFollower, np.ones(2, dtype=bool), False)
