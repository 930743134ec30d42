"""The author's Maze2D recipe (``evolution.generate.recipe: rollouts``): closed-loop rollouts that replan and end at
the goal, judged by the paper's rule on their real length, padded by staying at the goal; and evaluation with
replanning. Real simulator, tiny settings."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import maze_sim

from adaptdiffuser.checkpoint import make_bundle
from adaptdiffuser.config import (
    ConfigError,
    DiscriminateParams,
    GenerateParams,
    Params,
    apply_profile,
    params_from_dict,
)
from adaptdiffuser.contract import TaskFiles, TrackedTrajectory
from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.data.windows import WindowDataset
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.diffusion.samplers import DDIMSampler
from adaptdiffuser.evaluation import run_episodes
from adaptdiffuser.evolution.discriminator import QuantileRule, TopKRule
from adaptdiffuser.families.maze2d.evolution import judge_rollouts, stay_after_arrival
from adaptdiffuser.families.maze2d.execution import PlannerController
from adaptdiffuser.families.maze2d.generation import NavigationTasks, task_trajectories
from adaptdiffuser.families.maze2d.rollouts import ERROR_COLUMN, real_length, run_rollouts, settle_at_goal
from adaptdiffuser.families.maze2d.selection import PAPER_MAZE_RULES, PaperReturnClause, RolloutRule
from adaptdiffuser.families.maze2d.tasks import sample_navigation_tasks
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.planning import Planner

PROFILES = Path(__file__).resolve().parents[1] / "profiles"
TASK = "maze2d-umaze"
CPU = torch.device("cpu")
H = 32  # the smoke profile's horizon


class StraightLinePlanner:
    """A stand-in planner that draws a straight line from start to goal (through walls, if any), or by way of the
    coin when guided toward one, and records what it was asked: with it, rollouts between cells that see each other
    reach the goal, and the others get stuck."""

    act_dim = 2
    horizon = H
    device = CPU

    def __init__(self) -> None:
        self.calls: list[tuple[np.ndarray, list[int], bool]] = []

    def plan(self, starts: np.ndarray, goals: np.ndarray, seeds: list[int], guidance: object = None) -> np.ndarray:
        self.calls.append((np.array(starts), list(seeds), guidance is not None))
        f = np.linspace(0.0, 1.0, self.horizon)[None, :, None]
        if guidance is None:
            xy = starts[:, None, :2] + f * (goals[:, None, :2] - starts[:, None, :2])
        else:  # guided toward a coin: straight to the coin in the first half, then to the goal
            coins = guidance.coins.double().numpy()[:, None, :]
            half = np.minimum(2 * f, 1.0)
            xy = starts[:, None, :2] + half * (coins - starts[:, None, :2])
            xy = xy + np.clip(2 * f - 1, 0.0, 1.0) * (goals[:, None, :2] - coins)
        v = np.gradient(xy, axis=1) / 0.01
        v[:, -1] = 0.0
        return np.concatenate([np.zeros((len(starts), self.horizon, 2)), xy, v], axis=2)

    def guidance(self, objective: object, alpha: float) -> object:
        return objective


def rollout_params(tmp_path: Path, episode_steps: int = 80, **generate: object) -> Params:
    """The smoke profile with the rollouts recipe for U-Maze and short episodes."""
    raw = yaml.safe_load(apply_profile("smoke", PROFILES, tmp_path / "params.yaml").read_text())
    entry = raw["task"][TASK]
    entry["env"] = {**entry.get("env", {}), "episode_steps": episode_steps}
    raw["evolution"]["generate"] |= {"recipe": "rollouts", "replan_every": 8, **generate}
    return params_from_dict(raw)


def cell_tasks(pairs: list[tuple[tuple[int, int], tuple[int, int]]], coins: list | None = None) -> NavigationTasks:
    env = maze_sim()
    return NavigationTasks(
        starts=np.array([[*env.cell_to_xy(a), 0.0, 0.0] for a, _ in pairs]),
        goals=np.array([[*env.cell_to_xy(b), 0.0, 0.0] for _, b in pairs]),
        start_cells=np.array([a for a, _ in pairs]),
        goal_cells=np.array([b for _, b in pairs]),
        coins=None if coins is None else np.array(coins, dtype=np.float64),
    )


def tiny_planner(dtype: torch.dtype = torch.float32) -> Planner:
    torch.manual_seed(0)
    normalizer = MinMaxNormalizer(np.array([-1, -1, -2, -2, -5, -5.0]), np.array([1, 1, 2, 2, 5, 5.0]))
    params = Params()
    task = params.resolve(TASK)
    bundle = make_bundle(params.model, type(task.diffusion)(horizon=16, n_steps=4), 4, 2, normalizer)
    bundle.ema.to(dtype)
    return Planner(bundle, DDIMSampler(2), CPU)


def rollout(steps_to_goal: int, length: int | None = None) -> TrackedTrajectory:
    """A made-up executed rollout: at the goal first after ``steps_to_goal`` steps (-1: never, ``length`` steps)."""
    n = (steps_to_goal if steps_to_goal >= 0 else length) + 1
    rewards = np.zeros(n)
    if steps_to_goal >= 0:
        rewards[steps_to_goal:] = 1.0
    obs = np.zeros((n, 4))
    obs[:, 0] = np.linspace(0.0, 1.0, n)
    obs[:, 2] = 1.0
    return TrackedTrajectory(obs, np.ones((n, 2)), np.zeros(n - 1), rewards, steps_to_goal)


# -- (a) selection on real lengths --------------------------------------------------------------------------------


def test_rollout_rule_keeps_rollouts_that_reach_the_goal_early_by_their_real_length() -> None:
    early, late, never, slow = rollout(60), rollout(150), rollout(-1, 300), rollout(250)
    judged = [early, late, never, slow]
    returns = np.array([t.total_reward for t in judged])
    lengths = np.array([real_length(t) for t in judged])
    assert lengths.tolist() == [60, 150, 300, 250] and returns.tolist() == [1, 1, 0, 1]
    paper = RolloutRule(PaperReturnClause(300, 210.0), 300, rank_by_episode_return=False)
    # R + (300 - L) > 210 keeps L <= 90 (the protocol's return of an episode at the goal from step L on); the slow
    # one and the one that never arrives are not kept, though the whole paper rule's L > 200 clause would keep both
    assert paper.select(returns, lengths).tolist() == [0]
    assert PAPER_MAZE_RULES["umaze"].select(returns, lengths).tolist() == [0, 2, 3]
    # generic rules rank the rollouts that arrive by that same episode return: the shortest first
    assert RolloutRule(TopKRule(2), 300, True).select(returns, lengths).tolist() == [0, 1]
    assert RolloutRule(QuantileRule(1.0), 300, True).select(returns, lengths).tolist() == [0]
    assert RolloutRule(TopKRule(2), 300, True).select(np.zeros(2), np.array([300, 300])).tolist() == []


def test_the_paper_rule_on_arrival_times_keeps_the_shorter_paths_on_every_maze() -> None:
    """Read on the steps a rollout took to arrive, the whole paper rule keeps only the slowest arrivals on Medium
    (L > 450: with R = 1 its return clause needs L < 201, its length clause L > 200); the return clause alone, which
    the rollouts recipe applies under ``rule: paper``, keeps arrivals within 90 / 200 / 400 steps."""
    arrivals = np.array([50, 90, 91, 150, 200, 201, 300, 400, 401, 500, 700])
    for maze, within in (("umaze", 90), ("medium", 200), ("large", 400)):
        name = f"maze2d-{maze}"
        one_task = {"tasks": [name], "unseen_tasks": [name], "collect_tasks": [name], "evolve": name}
        params = params_from_dict({**one_task, "task": {name: {"family": "maze2d", "env": {"maze": maze}}}})
        resolved = params.resolve(name)
        cut = arrivals[arrivals < resolved.settings.episode_steps]
        rule = get_family("maze2d").selection_rule(resolved, DiscriminateParams(rule="paper"), "rollouts")
        kept = cut[rule.select(np.ones(len(cut)), cut)]
        assert kept.tolist() == cut[cut <= within].tolist(), maze
    literal = PAPER_MAZE_RULES["medium"]
    assert [n for n in range(1, 600) if literal.keeps(1.0, n)] == list(range(451, 600))


def expert_rollout(start: tuple[int, int], goal: tuple[int, int], max_steps: int = 300) -> TrackedTrajectory:
    """The waypoint expert from ``start`` to ``goal``, ending when it first reaches the goal (or after
    ``max_steps``), recorded as a rollout."""
    env = maze_sim()
    env.set_goal(goal)
    obs = env.reset(np.random.default_rng(0), cell=start)
    states, actions, rewards = [obs], [], [env.reward(obs)]
    while rewards[-1] == 0 and len(actions) < max_steps:
        actions.append(env.expert_action(obs))
        obs = env.step(actions[-1]).observation
        states.append(obs)
        rewards.append(env.reward(obs))
    r = np.asarray(rewards)
    hits = np.flatnonzero(r > 0)
    return TrackedTrajectory(
        np.asarray(states),
        np.asarray([*actions, np.zeros(2)]),
        np.zeros(len(actions)),
        r,
        int(hits[0]) if len(hits) else -1,
    )


def test_judge_rollouts_prefers_the_rollout_that_arrives_sooner(tmp_path: Path) -> None:
    params = rollout_params(tmp_path, episode_steps=300)
    task = params.resolve(TASK)
    family = get_family("maze2d")
    near = expert_rollout((1, 2), (1, 1))  # next cell: a few dozen steps
    far = expert_rollout((3, 1), (1, 1))  # the other end of the U: slower
    stuck = expert_rollout((3, 1), (1, 1), max_steps=40)  # cut short: never arrives
    assert 0 < near.steps_to_goal < far.steps_to_goal and stuck.steps_to_goal == -1
    tasks = NavigationTasks(
        starts=np.stack([t.observations[0] for t in (near, far, stuck)]),
        goals=np.tile([*maze_sim().cell_to_xy((1, 1)), 0.0, 0.0], (3, 1)),
        start_cells=np.zeros((0, 2)),
        goal_cells=np.zeros((0, 2)),
    )
    generated = task_trajectories([near, far, stuck], tasks, np.arange(3), TASK, {"recipe": "rollouts"})
    for cfg, kept in ((DiscriminateParams(rule="top_k", top_k=1), [0]), (DiscriminateParams(rule="top_k"), [0, 1])):
        judgement = family.discriminate(task, generated, cfg, 1, TaskFiles(tmp_path, TASK), progress=False)
        assert judgement.kept.tolist() == kept
        report = judgement.report()
        assert report["rejected_tracking"] == 0 and report["kept"] + report["rejected_reward"] == 3
    with pytest.raises(ValueError, match="tracking must be true"):
        judge_rollouts(maze_sim(), task, generated, DiscriminateParams(tracking=False), TopKRule(1))


# -- (b) rollouts: lengths, ends and padding ---------------------------------------------------------------------


def test_rollouts_vary_in_length_end_at_the_goal_or_the_limit_and_are_padded_by_staying(tmp_path: Path) -> None:
    params = rollout_params(tmp_path, episode_steps=80)
    task = params.resolve(TASK)
    family = get_family("maze2d")
    tasks = cell_tasks([((1, 1), (1, 3)), ((1, 1), (3, 1)), ((3, 3), (1, 3)), ((1, 2), (1, 1))])
    planner = StraightLinePlanner()
    rollouts = run_rollouts(lambda: family.make_simulator(task), planner, tasks, 5, 8, 80, batch_size=3)
    lengths = [len(r.observations) - 1 for r in rollouts]
    assert lengths[1] == 80 and rollouts[1].steps_to_goal == -1  # (1, 1) -> (3, 1) runs into the wall
    reached = [0, 2, 3]
    assert all(0 < rollouts[i].steps_to_goal == lengths[i] < 80 for i in reached)  # they end on arriving
    assert lengths[3] < lengths[0]  # the neighbouring cell is reached sooner
    assert all(r.rewards[-1] == 1.0 and (r.rewards[:-1] == 0).all() for r in (rollouts[i] for i in reached))
    # replanned every 8 steps, only the rollouts still going, each with the seed of its task and step
    assert [len(c[0]) for c in planner.calls[:2]] == [3, 3]
    assert planner.calls[1][1] == [derive_seed(5, i, 8) for i in range(3)]

    # the same through the family: generate -> discriminate -> selected data padded by staying at the goal
    cfg = params.phase(1)
    traj, stats = family.generate(task, planner, TaskFiles(tmp_path, TASK), cfg.generate, 0.0, 7, {}, False)
    assert stats["generated"] == cfg.generate.tasks and 0 < stats["rollout_reach_rate"] <= 1
    assert ERROR_COLUMN in traj.extra and len({ep.stop - ep.start for ep in traj.episodes()}) > 1
    judgement = family.discriminate(task, traj, cfg.discriminate, 1, TaskFiles(tmp_path, TASK), False)
    assert len(judgement.kept) and all(judgement.trajectories[i].rewards[-1] > 0 for i in judgement.kept)
    selected = family.selected_data(task, traj, judgement, {})
    windows = 0
    for i, ep in zip(judgement.kept, selected.episodes(), strict=True):
        kept = judgement.trajectories[i]
        n = len(kept.observations)
        assert ep.stop - ep.start == n + H - 1
        np.testing.assert_allclose(selected.observation[ep][: n - 1], kept.observations[:-1], atol=1e-6)
        rest = selected.observation[ep][n - 1 :]
        np.testing.assert_allclose(rest[:, :2], np.tile(kept.observations[-1, :2], (H, 1)), atol=1e-6)
        assert (rest[1:, 2:] == 0).all() and (selected.action[ep][n - 1 :] == 0).all()
        assert (selected.reward[ep][n - 1 :] == 1).all()
        windows += n  # every executed state starts a window of the horizon
    assert len(WindowDataset(selected, H, MinMaxNormalizer(-5 * np.ones(6), 5 * np.ones(6)))) == windows


def test_coin_rollouts_pick_the_coin_before_they_end_at_the_goal(tmp_path: Path) -> None:
    params = rollout_params(tmp_path, episode_steps=120)
    task = params.resolve(TASK)
    family = get_family("maze2d")
    env = maze_sim()
    # the goal (1, 3) is passed on the way to the coin in (1, 1): the rollout goes on until it is back at the goal
    tasks = cell_tasks([((1, 2), (1, 3)), ((1, 2), (1, 3))], coins=[[np.nan, np.nan], env.cell_to_xy((1, 1))])
    planner = StraightLinePlanner()
    free, coin = run_rollouts(lambda: family.make_simulator(task), planner, tasks, 1, 8, 120, 2, alpha=1.0)
    assert len(coin.observations) > len(free.observations)
    assert np.linalg.norm(coin.observations[:, :2] - env.cell_to_xy((1, 1)), axis=1).min() <= 0.5
    assert coin.rewards[-1] == 1.0
    assert planner.calls[0][2] is False  # the plain rollout and the coin one are planned apart, guided or not


# -- (c) reproducible and independent of the batch size ----------------------------------------------------------


def test_rollouts_are_reproducible_and_do_not_depend_on_the_batch_size() -> None:
    params = Params()
    task = params.resolve(TASK)
    family = get_family("maze2d")
    env = maze_sim()
    tasks = sample_navigation_tasks(env, 5, np.random.default_rng(3))
    # float64: no CPU's choice of kernels by batch size shows in the plans (see test_batch_independence), so the
    # closed loop cannot amplify it into another arrival step
    planner = tiny_planner(torch.float64)

    def rollouts(batch_size: int, seed: int = 11) -> list[TrackedTrajectory]:
        return run_rollouts(lambda: family.make_simulator(task), planner, tasks, seed, 4, 40, batch_size)

    alone = rollouts(1)
    for batch_size in (5, 2):
        other = rollouts(batch_size)
        for a, b in zip(alone, other, strict=True):
            assert len(a.observations) == len(b.observations) and a.steps_to_goal == b.steps_to_goal
            np.testing.assert_allclose(a.observations, b.observations, rtol=0.0, atol=1e-9)
    again = rollouts(5)
    for a, b in zip(rollouts(5), again, strict=True):
        np.testing.assert_array_equal(a.observations, b.observations)
        np.testing.assert_array_equal(a.actions, b.actions)
    assert not np.allclose(rollouts(5, seed=12)[0].observations[:20], alone[0].observations[:20])


# -- (d) settings -----------------------------------------------------------------------------------------------


def test_recipe_settings_are_checked_with_one_line_naming_the_key(tmp_path: Path) -> None:
    assert GenerateParams().recipe == "plans"  # the default: today's recipe
    with pytest.raises(
        ConfigError, match=r"^phases\.phase1\.generate\.recipe: 'rollout' is not a recipe of the maze2d family"
    ):
        rollout_params(tmp_path, recipe="rollout")
    with pytest.raises(ConfigError, match=r"^phases\.phase1\.generate\.replan_every: 40 exceeds diffusion"):
        rollout_params(tmp_path, replan_every=40)
    raw = yaml.safe_load((tmp_path / "params.yaml").read_text())
    raw["task"][TASK]["evolution"] = {"recipe": "rollouts"}  # no longer a key of the task's entry
    with pytest.raises(ConfigError, match=r"^task\.maze2d-umaze\.evolution\.recipe: unknown key"):
        params_from_dict(raw)
    raw["task"][TASK]["evolution"] = {}
    raw["evolution"]["generate"]["recipe"] = "rollouts"
    raw["evolution"]["discriminate"]["tracking"] = False
    with pytest.raises(ConfigError, match=r"^phases\.phase1\.discriminate\.tracking: .*rollouts"):
        params_from_dict(raw)
    params = rollout_params(tmp_path, replan_every=0)
    assert params.phase(1).generate.replan_every == 0  # plan once per rollout
    task = params.resolve(TASK)
    rule = get_family("maze2d").selection_rule(task, DiscriminateParams(rule="paper"), "rollouts")
    assert rule == RolloutRule(PaperReturnClause(300, 210.0), 80, rank_by_episode_return=False)
    assert get_family("maze2d").selection_rule(task, DiscriminateParams(rule="paper")) is PAPER_MAZE_RULES["umaze"]
    # a family without the recipe refuses it by name
    raw = yaml.safe_load(apply_profile("quick-locomotion", PROFILES, tmp_path / "locomotion.yaml").read_text())
    raw["evolution"]["generate"]["recipe"] = "rollouts"
    with pytest.raises(
        ConfigError, match=r"^phases\.phase1\.generate\.recipe: 'rollouts' is not a recipe of the locomotion"
    ):
        params_from_dict(raw)


# -- the plans recipe's optional stay at the goal ----------------------------------------------------------------


def test_settle_at_goal_and_plans_cut_where_they_arrive() -> None:
    obs = np.zeros((22, 4))
    obs[:, 0], obs[:, 2] = np.arange(22) / 10, 1.0
    obs[15, 1] = 5.0  # the coin's place
    rewards = np.zeros(22)
    rewards[[10, 11]] = 1.0  # arrives at step 10, drifts out at 12 and is back at 17
    rewards[17:] = 1.0
    t = TrackedTrajectory(obs, np.ones((22, 2)), np.ones(21), rewards, 10)
    cut = stay_after_arrival(t, None, 0.5)
    assert len(cut.observations) == 22 and cut.steps_to_goal == 10
    np.testing.assert_array_equal(cut.observations[:11], obs[:11])
    assert (cut.observations[11:, :2] == obs[10, :2]).all() and (cut.observations[11:, 2:] == 0).all()
    assert (cut.actions[:10] == 1).all() and (cut.actions[10:] == 0).all()
    assert (cut.rewards[10:] == 1).all() and (cut.errors[10:] == 0).all()
    # a coin task arrives only after its coin: the goal visit before it is not the arrival
    later = stay_after_arrival(t, obs[15, :2], 0.01)
    np.testing.assert_array_equal(later.observations[:18], obs[:18])
    assert (later.observations[18:, :2] == obs[17, :2]).all()
    assert stay_after_arrival(t, np.array([9.0, 9.0]), 0.5) is t  # never picks its coin: unchanged
    assert len(settle_at_goal(t, 21, 22 + 5).observations) == 27
    with pytest.raises(ValueError, match="stop must index"):
        settle_at_goal(t, 22, 30)


# -- evaluation with replanning ----------------------------------------------------------------------------------


def test_maze_evaluation_replans_from_the_current_state_every_replan_every_steps(tmp_path: Path) -> None:
    params = Params()
    task = params.resolve(TASK)
    family = get_family("maze2d")
    planner = StraightLinePlanner()
    controller = PlannerController(planner, 1000, replan_every=100)
    result = run_episodes(lambda: family.make_simulator(task), controller, 2, 1000, 2, progress=False)
    assert [len(c[0]) for c in planner.calls] == [2, 2, 2]  # t = 0, 100, 200 of a 300-step episode
    assert planner.calls[2][1] == [derive_seed(1000, e, 200) for e in (0, 1)]
    for e in range(2):
        np.testing.assert_allclose(planner.calls[1][0][e], result.executed[e][100])  # from where the agent is
    once = run_episodes(
        lambda: family.make_simulator(task), PlannerController(StraightLinePlanner(), 1000), 2, 1000, 2, progress=False
    )
    assert once.starts[0].tolist() == result.starts[0].tolist()
