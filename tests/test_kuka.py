"""The KUKA family on real PyBullet: suction, the stacking and pick-and-place criteria, the scripted demonstrator,
determinism, the state-only dataset and the pick-and-place guidance."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from adaptdiffuser.config import DiscriminateParams, load_params
from adaptdiffuser.data.schema import Trajectories, read_trajectories, write_trajectories
from adaptdiffuser.evaluation import run_episodes
from adaptdiffuser.families.kuka.dataset import state_episodes
from adaptdiffuser.families.kuka.demonstrator import (
    DemonstratorController,
    collect_demonstrations,
    record_demonstration,
    stacking_order,
)
from adaptdiffuser.families.kuka.evolution import (
    SETUP_COLUMN,
    MinReturnRule,
    execute_plan,
    judge_episodes,
    within_range,
)
from adaptdiffuser.families.kuka.execution import (
    PlaceObjective,
    block_to_place,
    commands_following_blocks,
    plan_commands,
)
from adaptdiffuser.families.kuka.params import ControlSettings, KukaTaskParams
from adaptdiffuser.families.kuka.scene import (
    BLOCK_HALF,
    FLAG_COLUMNS,
    HOME_JOINTS,
    N_JOINTS,
    OBS_DIM,
    block_position_columns,
    covered_blocks,
)
from adaptdiffuser.families.kuka.simulator import KukaSimulator
from adaptdiffuser.families.kuka.tasks import (
    PLACE_TARGETS,
    block_flags,
    block_positions,
    placed_count,
    stacked_count,
    tower_blocks,
)

SETTINGS = KukaTaskParams()


@pytest.fixture
def sim() -> KukaSimulator:
    simulator = KukaSimulator(SETTINGS)
    yield simulator
    simulator.close()


def move_cup(sim: KukaSimulator, cup: np.ndarray, flags: np.ndarray, steps: int = 40) -> np.ndarray:
    """Drive the cup to ``cup`` (inverse kinematics, position control) with the given suction flags."""
    joints = sim.get_state()[:N_JOINTS]
    for _ in range(steps):
        joints = sim.scene.inverse_kinematics(cup, joints)
        obs = sim.step(np.concatenate([joints, flags])).observation
    return obs


def test_dimensions_and_start(sim: KukaSimulator) -> None:
    obs = sim.reset(np.random.default_rng(0))
    assert obs.shape == (OBS_DIM,) == (39,)
    assert sim.act_dim == 11
    pos = block_positions(obs)
    assert np.allclose(pos[:, 2], BLOCK_HALF[2], atol=2e-3)  # on the floor
    radius = np.linalg.norm(pos[:, :2], axis=1)
    assert np.all((radius >= 0.35 - 1e-9) & (radius <= 0.6 + 1e-9))
    assert min(np.linalg.norm(pos[i, :2] - pos[j, :2]) for i in range(4) for j in range(i)) >= 0.3
    assert not block_flags(obs).any() and stacked_count(obs) == 0


def test_suction_attaches_carries_and_releases(sim: KukaSimulator) -> None:
    obs = sim.reset(np.random.default_rng(1))
    block = block_positions(obs)[2]
    top = block + np.array([0.0, 0.0, BLOCK_HALF[2] + 0.005])
    flags_on = np.array([0.0, 0.0, 1.0, 0.0])
    obs = move_cup(sim, top + [0, 0, 0.2], np.zeros(4))
    obs = move_cup(sim, top, np.zeros(4))
    assert block_flags(obs)[2] == 0.0  # the flag of the plan, not proximity, switches the cup on
    obs = move_cup(sim, top, flags_on, steps=3)
    assert block_flags(obs).tolist() == [0.0, 0.0, 1.0, 0.0]
    obs = move_cup(sim, top + [0, 0, 0.25], flags_on)
    assert block_positions(obs)[2, 2] > 0.2  # carried up with the cup
    assert np.allclose(block_positions(obs)[[0, 1, 3]], block_positions(sim.scene.observation())[[0, 1, 3]])
    obs = move_cup(sim, top + [0, 0, 0.25], np.zeros(4), steps=30)  # released: it falls back to the floor
    assert block_flags(obs)[2] == 0.0
    assert block_positions(obs)[2, 2] == pytest.approx(BLOCK_HALF[2], abs=0.01)


def test_suction_needs_the_block_within_reach(sim: KukaSimulator) -> None:
    obs = sim.reset(np.random.default_rng(2))
    far = block_positions(obs)[0] + np.array([0.0, 0.0, 0.35])  # well above the block
    obs = move_cup(sim, far, np.array([1.0, 1.0, 1.0, 1.0]))
    assert not block_flags(obs).any()
    assert np.allclose(block_positions(obs)[:, 2], BLOCK_HALF[2], atol=2e-3)


def settled_tower(sim: KukaSimulator, seed: int = 3) -> np.ndarray:
    """Start ``sim`` with the four blocks in one tower and let it settle; the observation."""
    obs = sim.start(HOME_JOINTS, tower_blocks(np.random.default_rng(seed), (0.35, 0.6)))
    for _ in range(20):
        obs = sim.step(np.concatenate([obs[:N_JOINTS], np.zeros(4)])).observation
    return obs


@pytest.mark.parametrize("max_joint_step", [None, 0.1])
def test_a_joint_step_limit_slows_a_far_target_to_that_step(max_joint_step: float | None) -> None:
    settings = KukaTaskParams(control={"max_joint_step": max_joint_step})
    sim = KukaSimulator(settings)
    try:
        start = sim.reset(np.random.default_rng(0))[:N_JOINTS]
        target = start + np.array([1.0, -0.8, 0.0, 0.0, 0.0, 0.0, 0.0])  # a jump no demonstration makes
        moved = sim.step(np.concatenate([target, np.zeros(4)])).observation[:N_JOINTS] - start
        if max_joint_step is None:
            assert np.abs(moved).max() > 0.25  # the unlimited arm swings far in one plan step
        else:
            assert np.abs(moved).max() <= max_joint_step + 0.02
            assert moved[0] > 0.05 and moved[1] < -0.05  # toward the target, each joint up to the limit
    finally:
        sim.close()
    with pytest.raises(ValueError, match="max_joint_step"):
        KukaTaskParams(control={"max_joint_step": 0.0})


def test_covered_blocks_are_those_with_a_block_on_them() -> None:
    tower = tower_blocks(np.random.default_rng(0), (0.35, 0.6))[:, :3]
    assert covered_blocks(tower).tolist() == [True, True, True, False]
    side_by_side = tower.copy()
    side_by_side[3, 0] += 0.25  # the top block beside the tower, still high: it covers nothing now
    assert covered_blocks(side_by_side).tolist() == [True, True, False, False]


@pytest.mark.parametrize("free_top_only", [False, True])
def test_with_free_tops_the_cup_takes_no_block_from_under_another(free_top_only: bool) -> None:
    sim = KukaSimulator(KukaTaskParams(control=ControlSettings(free_top_only=free_top_only)))
    obs = settled_tower(sim)
    top = block_positions(obs)[3] + np.array([0.0, 0.0, BLOCK_HALF[2] + 0.005])  # on the tower's top block
    obs = move_cup(sim, top + [0, 0, 0.2], np.zeros(4))
    obs = move_cup(sim, top, np.array([0.0, 0.0, 1.0, 0.0]))  # asks for block 2, under block 3 but within reach
    sim.close()
    assert block_flags(obs)[2] == (0.0 if free_top_only else 1.0)


def test_following_the_blocks_takes_the_real_block_and_carries_it_where_the_plan_does(sim: KukaSimulator) -> None:
    obs = sim.reset(np.random.default_rng(4))
    planned = obs.copy()
    planned[:N_JOINTS] = HOME_JOINTS  # planned joints that would leave the cup where it is
    where = block_position_columns(2)
    planned[where] += [0.3, 0.0, 0.0]  # an imagined block 2, away from the real one
    planned[FLAG_COLUMNS[2]] = 1.0
    np.testing.assert_array_equal(commands_following_blocks([sim.scene], obs[None], obs[None])[0], plan_commands(obs))
    for _ in range(40):
        obs = sim.step(commands_following_blocks([sim.scene], obs[None], planned[None])[0]).observation
    assert block_flags(obs).tolist() == [0.0, 0.0, 1.0, 0.0]  # the cup went to the real block and took it
    planned[where] = block_positions(obs)[2] + [0.0, 0.1, 0.25]  # the plan carries it up and aside
    for _ in range(40):
        obs = sim.step(commands_following_blocks([sim.scene], obs[None], planned[None])[0]).observation
    np.testing.assert_allclose(block_positions(obs)[2], planned[where], atol=0.02)


def test_following_the_blocks_leaves_a_covered_block_to_the_planned_joints(sim: KukaSimulator) -> None:
    obs = settled_tower(sim)
    planned = obs.copy()
    planned[FLAG_COLUMNS[1]] = 1.0  # block 1 is under blocks 2 and 3
    np.testing.assert_array_equal(
        commands_following_blocks([sim.scene], obs[None], planned[None])[0], plan_commands(planned)
    )


def test_stacked_and_placed_counts_with_real_physics(sim: KukaSimulator) -> None:
    tower = tower_blocks(np.random.default_rng(3), (0.35, 0.6))
    obs = sim.start(np.zeros(N_JOINTS) + [0, 0.3, 0, -1.5, 0, 1.2, 0], tower)
    for _ in range(20):  # let the tower settle
        obs = sim.step(np.concatenate([obs[:N_JOINTS], np.zeros(4)])).observation
    assert stacked_count(obs) == 3
    held = obs.copy()
    held[FLAG_COLUMNS[3]] = 1.0  # a carried block does not count
    assert stacked_count(held) == 2
    state = obs.copy()
    for i in range(4):
        cols = block_position_columns(i)
        state[cols] = PLACE_TARGETS[i] + [0.12 if i == 0 else 0.0, 0.0, 0.0]  # block 0 off by 0.12: still within 0.2
    state[list(FLAG_COLUMNS)] = 0.0
    placed = sim.set_state(state)
    assert placed_count(placed) == 4
    state[block_position_columns(1)] = PLACE_TARGETS[1] + [0.25, 0.0, 0.0]  # too far from its target
    assert placed_count(sim.set_state(state)) == 3
    carried = state.copy()
    carried[FLAG_COLUMNS[0]] = 1.0
    assert placed_count(carried) == 2


def test_the_free_order_takes_a_tower_from_the_top_and_keeps_a_carried_block(sim: KukaSimulator) -> None:
    tower = tower_blocks(np.random.default_rng(3), (0.35, 0.6))
    obs = sim.start(np.zeros(N_JOINTS) + [0, 0.3, 0, -1.5, 0, 1.2, 0], tower)
    for _ in range(20):  # let the tower settle
        obs = sim.step(np.concatenate([obs[:N_JOINTS], np.zeros(4)])).observation
    assert block_to_place(obs) == 3  # block 0 is the bottom: only the top is free
    carried = obs.copy()
    carried[FLAG_COLUMNS[2]] = 1.0
    assert block_to_place(carried) == 2  # the held block stays the one to move
    scattered = obs.copy()
    for i in range(4):
        scattered[block_position_columns(i)] = [0.0, 0.4 + 0.3 * i, 0.03]
    assert block_to_place(scattered) == 0
    scattered[block_position_columns(0)] = PLACE_TARGETS[0]  # block 0 on its target: the next one
    scattered[block_position_columns(1)] = PLACE_TARGETS[1]
    assert block_to_place(scattered) == 2
    for i in range(4):
        scattered[block_position_columns(i)] = PLACE_TARGETS[i]
    assert block_to_place(scattered) == 0  # all placed: block 0


def test_demonstrator_stacks_and_the_return_is_the_final_count() -> None:
    """The scripted demonstrator as an evaluation controller: each step's reward is the change of the stacked
    count, so the return is the final count (a full tower: 3), in each episode's own shuffled order."""
    d = SETTINGS.demonstrator
    controller = DemonstratorController(d.speed, d.safe_height, d.dwell, order_seed=3)
    result = run_episodes(lambda: KukaSimulator(SETTINGS, episode_steps=460), controller, 2, 7, 2, progress=False)
    for executed, ret in zip(result.executed, result.returns, strict=True):
        assert stacked_count(executed[0]) == 0
        assert ret == stacked_count(executed[-1]) == 3


@pytest.mark.parametrize("order", ["shuffled", "in_turn"])
def test_demonstrations_build_the_tower_in_their_order(order: str) -> None:
    """Shuffled demonstrations stack their own random order (a different base block across seeds); in turn, blocks
    1, 2, 3 go onto block 0."""
    settings = KukaTaskParams(demonstrator={"rest_steps": 2, "order": order})
    sim = KukaSimulator(settings)
    bases = set()
    for seed in range(4):
        demo = record_demonstration(sim, np.random.default_rng([11, seed]), settings)
        replay = np.random.default_rng([11, seed])
        sim.reset(replay)  # the order is drawn after the start, from the same generator
        expected = stacking_order(replay if order == "shuffled" else None)
        heights = block_positions(demo[-1])[:, 2]
        assert stacked_count(demo[-1]) == 3
        assert list(np.argsort(heights)) == list(expected)
        bases.add(int(expected[0]))
    assert (len(bases) > 1) == (order == "shuffled")
    sim.close()


def test_same_seed_same_episode() -> None:
    runs = []
    for _ in range(2):
        sim = KukaSimulator(SETTINGS)
        runs.append(record_demonstration(sim, np.random.default_rng([5, 1]), SETTINGS))
        sim.close()
    assert runs[0].shape == runs[1].shape
    assert np.array_equal(runs[0], runs[1])
    other = record_demonstration(KukaSimulator(SETTINGS), np.random.default_rng([5, 2]), SETTINGS)
    assert not np.array_equal(other[0], runs[0][0])


def test_state_only_dataset_round_trip(tmp_path) -> None:
    settings = KukaTaskParams(collect={"episodes": 2, "seed": 0}, demonstrator={"rest_steps": 3})
    sim = KukaSimulator(settings)
    traj, figures = collect_demonstrations(sim, settings, "kuka-stacking", progress=False)
    assert traj.action.shape == (len(traj), 0) and traj.metadata["act_dim"] == 0
    path = tmp_path / "data.parquet"
    write_trajectories(path, traj)
    back = read_trajectories(path, env="kuka-stacking")
    assert back.action.shape == (len(traj), 0)
    np.testing.assert_allclose(back.observation, traj.observation)
    episodes = back.episodes()
    assert len(episodes) == 2
    finals = [stacked_count(back.observation[ep][-1]) for ep in episodes]
    assert figures["stacked_mean"] == np.mean(finals) and max(finals) == 3
    for ep, final in zip(episodes, finals, strict=True):  # rewards sum to the final count; the last row ends it
        assert back.reward[ep].sum() == final
        assert back.timeout[ep][-1] and not back.timeout[ep][:-1].any()


def test_place_objective_prefers_plans_nearer_the_target() -> None:
    horizon, block = 10, 1
    states = torch.zeros(2, horizon, OBS_DIM)
    cols = block_position_columns(block)
    start = torch.tensor([-0.4, 0.3])
    target = torch.tensor(PLACE_TARGETS[block, :2], dtype=torch.float32)
    for t in range(horizon):  # plan 0 drifts to the target, plan 1 stays at the start
        states[0, t, cols.start : cols.start + 2] = start + (target - start) * t / (horizon - 1)
        states[1, t, cols.start : cols.start + 2] = start
    objective = PlaceObjective([block, block], first=5)
    values = objective(states)
    assert values[0] > values[1]
    moved = states.clone().requires_grad_(True)
    objective(moved).sum().backward()
    grad = moved.grad
    assert grad[:, :5].abs().sum() == 0  # the first half is free
    assert grad[1, 5:, cols.start].gt(0).all()  # pulls x toward the target's 0.5
    others = [c for c in range(OBS_DIM) if c not in (cols.start, cols.start + 1)]
    assert grad[:, :, others].abs().sum() == 0


def test_plan_commands_take_joints_and_flags() -> None:
    plan = np.arange(2 * 3 * OBS_DIM, dtype=float).reshape(2, 3, OBS_DIM)
    commands = plan_commands(plan)
    assert commands.shape == (2, 3, 11)
    np.testing.assert_array_equal(commands[..., :N_JOINTS], plan[..., :N_JOINTS])
    np.testing.assert_array_equal(commands[..., N_JOINTS:], plan[..., list(FLAG_COLUMNS)])


def test_kuka_settings_are_checked() -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="inner < outer"):
        KukaTaskParams(scene={"radius": [0.6, 0.3]})
    with pytest.raises(ValidationError, match="substeps"):
        KukaTaskParams(control={"substeps": 0})
    with pytest.raises(ValueError, match="unknown KUKA task kind"):
        KukaSimulator(SETTINGS, kind="juggling")


def _as_generated(plans: list[np.ndarray]) -> Trajectories:
    return state_episodes(plans, "kuka-stacking", "synthetic", {}, per_episode={SETUP_COLUMN: np.ones(len(plans))})


def test_discriminator_executes_plans_and_rejects_what_the_simulator_cannot_do() -> None:
    """A real demonstration taken as a plan tracks and keeps its reward; a plan that teleports a block onto another
    (the arm idle) tracks but earns nothing, since the reward is the executed scene's; a plan whose joints jump is
    rejected; the paper's rule keeps more than 1.5."""
    sim = KukaSimulator(SETTINGS, episode_steps=1000)
    demo = record_demonstration(sim, np.random.default_rng([9, 0]), SETTINGS)
    teleport = np.repeat(demo[:1], 40, axis=0)
    teleport[1:, block_position_columns(1)] = demo[0, block_position_columns(0)] + [0.0, 0.0, 0.06]
    assert stacked_count(teleport[-1]) == 1  # the plan claims a stack
    jump = demo[:60].copy()
    jump[30:, 0] += 2.0  # the base joint jumps by 2 rad (position control covers about 0.6 rad per step)
    generated = _as_generated([demo, teleport, jump])
    cfg = DiscriminateParams(max_error=1.02, rule="paper")
    simulator = lambda task, kind, setup: KukaSimulator(SETTINGS, episode_steps=1000)  # noqa: E731
    judgement = judge_episodes(simulator, None, generated, cfg, demo, None, progress=False)
    demo_run, teleport_run, jump_run = judgement.trajectories
    assert demo_run.max_error < 1.02 and demo_run.total_reward == 3
    # commanded to the demonstration's recorded states (not its inverse-kinematics targets): the same outcome
    np.testing.assert_allclose(block_positions(demo_run.observations[-1]), block_positions(demo[-1]), atol=0.02)
    assert teleport_run.max_error < 1.02 and teleport_run.total_reward == 0
    assert jump_run.max_error > 1.02
    assert judgement.passed_tracking.tolist() == [True, True, False]
    assert judgement.kept.tolist() == [0]
    assert judgement.report()["off_plan"] == 1 and judgement.report()["out_of_range"] == 0
    # states outside the expert data's range (here: the demonstration before any block moved) are rejected, and the
    # report says which check did it
    before_lift = demo[:10]
    for excess, passed in ((0.25, [False]), (None, [True])):
        judged = judge_episodes(simulator, None, _as_generated([demo]), cfg, before_lift, excess, progress=False)
        assert judged.passed_tracking.tolist() == passed
        assert (judged.report()["off_plan"], judged.report()["out_of_range"]) == (0, int(not passed[0]))
    assert MinReturnRule(1.5).select(np.array([1.0, 2.0, 4.0, 1.5]), np.ones(4)).tolist() == [2, 1]


def test_following_execution_holds_the_plan_to_its_blocks_not_its_joints() -> None:
    """Executed by the blocks, a demonstration tracks (its blocks within 5 cm of the plan's); planned joints that go
    astray while a block is carried do not matter there (the joints are not aimed at), but fail the plain execution;
    a carried block that jumps fails, and so does a block the plan moves without carrying it."""
    sim = KukaSimulator(SETTINGS, episode_steps=1000)
    demo = record_demonstration(sim, np.random.default_rng([9, 0]), SETTINGS)
    holding = np.flatnonzero(block_flags(demo).max(axis=1) > 0.5)
    assert execute_plan(sim, demo, follow_blocks=True).max_error < 0.05
    astray = demo.copy()
    astray[holding, 0] += 2.0  # the base joint 2 rad off while carrying
    assert execute_plan(sim, astray, follow_blocks=True).max_error < 0.05
    assert execute_plan(sim, astray).max_error > 1.02
    jump = demo.copy()
    carried = int(np.argmax(block_flags(demo[holding[5]])))
    jump[holding[5] :, block_position_columns(carried)] += [1.5, 0.0, 0.0]
    assert execute_plan(sim, jump, follow_blocks=True).max_error > 1.0
    teleport = np.repeat(demo[:1], 40, axis=0)  # block 1 onto block 0, the arm idle: the real block stays
    teleport[1:, block_position_columns(1)] = demo[0, block_position_columns(0)] + [0.0, 0.0, 0.06]
    assert execute_plan(sim, teleport, follow_blocks=True).max_error > 0.5
    sim.close()


@pytest.mark.e2e
def test_generation_records_executed_plan_chains_and_the_discriminator_judges_them(smoke_repo, tmp_path) -> None:
    """Evolution's KUKA path on the smoke project's trained model: guided pick-and-place episodes of both setups
    (each a chain of plans, replanned from where the last one ended), written and read as Parquet, executed again
    by the discriminator, and the kept ones as a state-only dataset."""
    from adaptdiffuser.checkpoint import load_bundle
    from adaptdiffuser.config import GenerateParams
    from adaptdiffuser.contract import TaskFiles
    from adaptdiffuser.diffusion.samplers import make_sampler
    from adaptdiffuser.family_registry import get_family
    from adaptdiffuser.planning import Planner

    params = load_params(smoke_repo / "params.yaml")
    task = params.resolve("kuka-stacking")
    family = get_family("kuka")
    planner = Planner(load_bundle(smoke_repo / "models/kuka-stacking/phase0/seed0"), make_sampler("ddim", 2), "cpu")
    cfg = GenerateParams(tasks=5, batch_size=2)
    generated, stats = family.generate(task, planner, None, cfg, params.alpha, 11, {"phase": 1}, progress=False)
    steps = task.settings.pick_place.replans * (task.diffusion.horizon - 1)
    assert stats["generated"] == 5 and len(generated) == 5 * (steps + 1)
    assert generated.extra[SETUP_COLUMN][:: steps + 1].tolist() == [1, 1, 1, 2, 2]
    path = tmp_path / "generated.parquet"
    write_trajectories(path, generated)
    generated = read_trajectories(path, env="kuka-stacking")
    again, _ = family.generate(task, planner, None, cfg, params.alpha, 11, {"phase": 1}, progress=False)
    np.testing.assert_array_equal(again.observation, generated.observation)  # same seed, same plans
    unguided, _ = family.generate(task, planner, None, cfg, 0.0, 11, {"phase": 1}, progress=False)
    assert params.alpha > 0 and not np.array_equal(unguided.observation, generated.observation)  # alpha guides
    starts = generated.observation[:: steps + 1]
    assert np.allclose(block_positions(starts[3])[:, :2], block_positions(starts[3])[0, :2])  # setup 2: a tower
    cfg = DiscriminateParams(max_error=100.0, rule="quantile")
    expert = read_trajectories(smoke_repo / "data/kuka-stacking/dataset.parquet").observation
    judgement = judge_episodes(family.make_simulator, task, generated, cfg, expert, None, progress=False)
    assert judgement.passed_tracking.all() and len(judgement.kept) >= 1
    # the family's discriminator adds the range check against the task's stacking data
    checked = family.discriminate(task, generated, cfg, 1, TaskFiles(smoke_repo, task.name), progress=False)
    excess = task.settings.selection.max_range_excess
    low, high = expert.min(axis=0), expert.max(axis=0)
    in_range = [within_range(t.observations, low, high, excess) for t in judgement.trajectories]
    assert excess == 0.25 and checked.passed_tracking.tolist() == in_range
    for tracked, start in zip(judgement.trajectories, starts, strict=True):  # executed from each plan's start
        np.testing.assert_allclose(tracked.observations[0], start, atol=1e-5)
    selected = family.selected_data(task, generated, judgement, {"phase": 1})
    assert selected.action.shape == (len(selected), 0) and len(selected.episodes()) == len(judgement.kept)
    write_trajectories(tmp_path / "selected.parquet", selected)
