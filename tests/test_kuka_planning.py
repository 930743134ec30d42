"""KUKA planning options with the real planner (a tiny untrained model, DDIM) and the real PyBullet scene: resting
blocks pinned to their real poses until the plan picks them up, and replanning more often than once per plan."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from adaptdiffuser.checkpoint import make_bundle
from adaptdiffuser.config import (
    ConfigError,
    DiffusionParams,
    ModelParams,
    apply_profile,
    params_from_dict,
    set_dotted,
)
from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.diffusion.samplers import DDIMSampler
from adaptdiffuser.evaluation import run_episodes
from adaptdiffuser.families.kuka.execution import (
    ReplanningController,
    held_block_condition,
    place_condition,
    place_guidance,
    placed_goal_condition,
    resting_blocks_pinned,
)
from adaptdiffuser.families.kuka.params import KukaTaskParams
from adaptdiffuser.families.kuka.scene import (
    BLOCK_DIMS,
    FLAG_COLUMNS,
    N_BLOCKS,
    N_JOINTS,
    OBS_DIM,
    block_position_columns,
)
from adaptdiffuser.families.kuka.simulator import KukaSimulator
from adaptdiffuser.families.kuka.tasks import PLACE_TARGETS
from adaptdiffuser.planning import Planner

HORIZON = 16


def pose_columns(block: int) -> list[int]:
    """A block's xyz and quaternion columns."""
    start = N_JOINTS + block * BLOCK_DIMS
    return list(range(start, start + 7))


class RecordingPlanner(Planner):
    """The real planner, keeping the starts it was asked to plan from, the plans it made and its projections."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.clear()

    def clear(self) -> None:
        self.starts: list[np.ndarray] = []
        self.plans: list[np.ndarray] = []
        self.projections: list = []
        self.guidances: list = []

    def plan(self, starts, goals, seeds, guidance=None, project=None) -> np.ndarray:
        plans = super().plan(starts, goals, seeds, guidance, project)
        self.starts.append(np.array(starts))
        self.plans.append(plans)
        self.projections.append(project)
        self.guidances.append(guidance)
        return plans


def tiny_planner(flag_high: float = 1.0) -> RecordingPlanner:
    """A tiny untrained KUKA model (states only) whose flags span [0, ``flag_high``] in raw units: its plans move
    the blocks at random, which is what pinning fixes."""
    torch.manual_seed(0)
    low, high = np.full(OBS_DIM, -1.0), np.full(OBS_DIM, 1.0)
    low[list(FLAG_COLUMNS)], high[list(FLAG_COLUMNS)] = 0.0, flag_high
    bundle = make_bundle(
        ModelParams(dim=8, dim_mults=[1, 2]), DiffusionParams(horizon=HORIZON, n_steps=8), OBS_DIM, 0,
        MinMaxNormalizer(low, high), conditioning="start",
    )  # fmt: skip
    return RecordingPlanner(bundle, DDIMSampler(4), torch.device("cpu"))


@pytest.fixture(scope="module")
def planner() -> RecordingPlanner:
    return tiny_planner()


def test_resting_blocks_keep_their_first_pose_until_their_flag_first_turns_on(planner: RecordingPlanner) -> None:
    x = torch.rand(2, HORIZON, OBS_DIM) * 2 - 1
    flags = [N_JOINTS + b * BLOCK_DIMS + 7 for b in range(N_BLOCKS)]
    x[:, :, flags] = -1.0  # 0 in raw units: off
    x[0, 3:, flags[0]] = 1.0  # block 0 picked at step 3
    x[0, 0:, flags[2]] = 0.8  # block 2 held from the start
    x[0, 5:7, flags[3]] = 0.5  # block 3 held over steps 5-6, then let go
    x[1, 9:, flags[1]] = 0.1  # just above 0.5 in raw units
    y = resting_blocks_pinned(planner)(x)

    first_on = {(0, 0): 3, (0, 1): HORIZON, (0, 2): 0, (0, 3): 5, (1, 0): HORIZON, (1, 1): 9}
    first_on |= {(1, 2): HORIZON, (1, 3): HORIZON}
    for (row, block), step in first_on.items():
        cols = pose_columns(block)
        assert torch.equal(y[row, :step, cols], x[row, :1, cols].expand(step, -1)), (row, block)
        assert torch.equal(y[row, step:, cols], x[row, step:, cols]), (row, block)
    others = [c for c in range(OBS_DIM) if all(c not in pose_columns(b) for b in range(N_BLOCKS))]
    assert torch.equal(y[:, :, others], x[:, :, others])  # joints and flags untouched


@pytest.mark.parametrize("flag_high", [1.0, 0.5])
def test_sampled_plans_leave_resting_blocks_where_they_are(flag_high: float) -> None:
    """With flags up to 1 the untrained model turns some on early; up to 0.5, never: every block rests throughout."""
    planner = tiny_planner(flag_high)
    sim = KukaSimulator(KukaTaskParams())
    start = sim.reset(np.random.default_rng(5))
    sim.close()
    starts = np.stack([start, start])
    free = planner.plan(starts, None, [1, 2])
    pinned = planner.plan(starts, None, [1, 2], project=resting_blocks_pinned(planner))
    assert np.allclose(free[:, 0], starts) and np.allclose(pinned[:, 0], starts)
    moved, pinned_steps = 0, 0
    for plans, is_pinned in ((free, False), (pinned, True)):
        for row in range(2):
            on = plans[row][:, list(FLAG_COLUMNS)] > 0.5
            for block in range(N_BLOCKS):
                step = int(np.argmax(on[:, block])) if on[:, block].any() else HORIZON
                cols = pose_columns(block)
                same = np.allclose(plans[row][:step][:, cols], starts[row, cols], atol=1e-5)
                if is_pinned:
                    assert same, (row, block, step)
                    pinned_steps += step
                moved += not same
    assert pinned_steps > 0
    if flag_high == 0.5:  # no flag on: without pinning the untrained model moves the resting blocks
        assert pinned_steps == 2 * N_BLOCKS * HORIZON and moved > 0


def test_replanning_every_k_steps_plans_from_the_real_state_and_records_what_it_commanded(
    planner: RecordingPlanner,
) -> None:
    every, span = 5, HORIZON - 1
    steps = 2 * span
    asked = []

    def guidance(stretch: int, offset: int, obs: np.ndarray) -> None:
        asked.append((stretch, offset, len(obs)))

    controller = ReplanningController(planner, seed=3, guidance=guidance, record=True, replan_every=every)
    planner.clear()
    result = run_episodes(
        lambda: KukaSimulator(KukaTaskParams(), episode_steps=steps), controller, 2, 9, 2, progress=False
    )
    assert len(planner.starts) == steps // every  # a plan every 5 steps: 6 plans for 30 steps
    assert asked == [(0, 0, 2), (0, 5, 2), (0, 10, 2), (1, 0, 2), (1, 5, 2), (1, 10, 2)]  # stretches of 15 steps
    executed = np.stack(result.executed)  # [episodes, steps + 1, 39]
    recorded = np.stack(controller.recorded)
    assert recorded.shape == executed.shape
    np.testing.assert_array_equal(recorded[:, 0], executed[:, 0])
    for k, (starts, plans) in enumerate(zip(planner.starts, planner.plans, strict=True)):
        np.testing.assert_array_equal(starts, executed[:, k * every])  # each plan starts from the observed state
        # step k * every + j was commanded plan k's state j + 1
        np.testing.assert_array_equal(recorded[:, k * every + 1 : (k + 1) * every + 1], plans[:, 1 : every + 1])
    with pytest.raises(ValueError, match="replan_every must be in"):
        ReplanningController(planner, seed=3, replan_every=HORIZON)


def test_the_task_planning_settings_reach_evaluation_and_pick_and_place(
    planner: RecordingPlanner, tmp_path: Path
) -> None:
    """The family's stacking controller and its pick-and-place evaluation both follow ``planning``."""
    from adaptdiffuser.family_registry import get_family

    task = params_from_dict(
        kuka_raw(
            {
                "diffusion.horizon": HORIZON,
                "planning": {"pin_resting_blocks": True, "replan_every": 5, "follow_blocks": True},
                "pick_place": {
                    "setups": [2],
                    "episodes": 1,
                    "batch_size": 1,
                    "next_block": "free",
                    "hold": [0.25, 0.75],
                },
            },
            tmp_path,
        )  # fmt: skip
    ).resolve("kuka-stacking")
    family = get_family("kuka")
    controller = family.controller(task, planner, None, planner.device)
    assert controller.every == 5 and controller.project is not None and controller.follow_blocks
    planner.clear()
    family.evaluate_unseen(task, planner, 1.0, {}, 0, "", False)
    plans_per_episode = task.settings.pick_place.replans * (HORIZON - 1) // 5
    assert len(planner.plans) == plans_per_episode and all(p is not None for p in planner.projections)
    tower_top = block_position_columns(N_BLOCKS - 1).start  # setup 2 starts as a tower: its top block goes first
    assert planner.guidances[0].objective.columns.tolist() == [tower_top]
    # pick_place.hold: the first plan holds the tower's top block over steps 4-11 of 16 (its projection is the
    # condition, then pinning)
    first = planner.plans[0]
    flags = first[:, :, list(FLAG_COLUMNS)]
    assert np.allclose(flags[0, 4:12, N_BLOCKS - 1], 1.0) and np.allclose(flags[0, 4:12, : N_BLOCKS - 1], 0.0)
    assert np.allclose(flags[0, 12:], 0.0)


def kuka_raw(task_settings: dict, tmp_path: Path) -> dict:
    """The quick-kuka profile's raw params, with these ``task.kuka-stacking`` keys (dotted or nested) set."""
    profiles = Path(__file__).resolve().parents[1] / "profiles"
    raw = yaml.safe_load(apply_profile("quick-kuka", profiles, tmp_path / "params.yaml").read_text())
    for key, value in task_settings.items():
        raw = set_dotted(raw, f"task.kuka-stacking.{key}", value)
    return raw


def test_replan_every_longer_than_a_plan_is_refused(tmp_path: Path) -> None:
    horizon = kuka_raw({}, tmp_path)["task"]["kuka-stacking"]["diffusion"]["horizon"]
    params_from_dict(kuka_raw({"planning.replan_every": horizon - 1}, tmp_path))  # a whole plan: accepted
    with pytest.raises(ConfigError, match="planning.replan_every"):
        params_from_dict(kuka_raw({"planning.replan_every": horizon}, tmp_path))


def test_pick_and_place_guidance_follows_the_stretch_not_the_plan(planner: RecordingPlanner) -> None:
    """A plan drawn part-way into a stretch guides that stretch's block over the stretch's guided steps."""
    make = place_guidance(planner, 2.0, first=8)
    obs = np.zeros((3, OBS_DIM))
    whole, late, past = make(1, 0, obs), make(1, 5, obs), make(6, 12, obs)
    assert whole.objective.first == 8 and late.objective.first == 3 and past.objective.first == 0
    assert whole.alpha == 2.0
    columns = [block_position_columns(b).start for b in (1, 1, 1)]
    assert (
        whole.objective.columns.tolist() == columns
        and past.objective.columns.tolist() == [block_position_columns(2).start] * 3
    )


def test_free_pick_and_place_guidance_moves_each_episodes_next_block(planner: RecordingPlanner) -> None:
    """With ``next_block: free`` each episode's plan guides the block its own scene needs next, whatever the
    stretch."""
    obs = np.zeros((2, OBS_DIM))
    for i in range(N_BLOCKS):
        obs[:, block_position_columns(i)] = [0.0, 0.4 + 0.3 * i, 0.03]
    obs[1, FLAG_COLUMNS[2]] = 1.0  # episode 1 carries block 2
    guided = place_guidance(planner, 2.0, first=8, next_block="free")(3, 0, obs)
    assert guided.objective.columns.tolist() == [block_position_columns(b).start for b in (0, 2)]
    with pytest.raises(ValueError, match="next_block"):
        place_guidance(planner, 2.0, first=8, next_block="random")


def test_the_hold_condition_holds_each_plans_block_over_its_steps_then_lets_go(planner: RecordingPlanner) -> None:
    """``held_block_condition``: plan i's block flag on (raw 1) and the others off (raw 0) over [first, last),
    every flag off from last on; nothing else changes; sampled plans keep it (inpainted at every step)."""
    x = torch.rand(2, HORIZON, OBS_DIM) * 2 - 1
    y = held_block_condition(planner, [2, 0], first=3, last=9)(x)
    raw = planner.normalizer.unnormalize(y.numpy())
    flags = raw[:, :, list(FLAG_COLUMNS)]
    expected = np.zeros((2, 6, N_BLOCKS))
    expected[0, :, 2], expected[1, :, 0] = 1.0, 1.0
    np.testing.assert_allclose(flags[:, 3:9], expected, atol=1e-6)
    np.testing.assert_allclose(flags[:, 9:], 0.0, atol=1e-6)
    assert torch.equal(y[:, :3], x[:, :3])  # before the hold: free
    others = [c for c in range(OBS_DIM) if c not in FLAG_COLUMNS]
    assert torch.equal(y[:, :, others], x[:, :, others])

    sim = KukaSimulator(KukaTaskParams())
    start = sim.reset(np.random.default_rng(5))
    sim.close()
    plans = planner.plan(np.stack([start, start]), None, [1, 2], project=held_block_condition(planner, [1, 3], 3, 9))
    assert (plans[0, 3:9, FLAG_COLUMNS[1]] > 0.5).all() and (plans[1, 3:9, FLAG_COLUMNS[3]] > 0.5).all()
    assert (plans[:, 9:, list(FLAG_COLUMNS)] < 0.5).all()


def test_the_hold_condition_follows_the_stretch_and_each_episodes_block(planner: RecordingPlanner) -> None:
    """A plan drawn part-way into a stretch holds that stretch's block over the stretch's steps, shifted; with
    ``free`` each episode holds the block its own scene needs next."""
    obs = np.zeros((2, OBS_DIM))
    for i in range(N_BLOCKS):
        obs[:, block_position_columns(i)] = [0.0, 0.4 + 0.3 * i, 0.03]
    obs[1, FLAG_COLUMNS[2]] = 1.0  # episode 1 carries block 2
    x = torch.zeros(2, HORIZON, OBS_DIM)
    late = place_condition(planner, first=4, last=12, next_block="free")(0, 6, obs)(x)
    flags = planner.normalizer.unnormalize(late.numpy())[:, :, list(FLAG_COLUMNS)]
    # its steps 1-5 are the stretch's 7-11; step 0, the real start, is left as it is
    assert torch.equal(late[:, 0], x[:, 0])
    assert np.allclose(flags[0, 1:6, 0], 1.0) and np.allclose(flags[1, 1:6, 2], 1.0)
    assert np.allclose(flags[0, 1:6, [1, 2, 3]], 0.0) and np.allclose(flags[:, 6:], 0.0)
    past = place_condition(planner, first=4, last=12)(0, 14, obs)(x)  # drawn after the span: every flag off
    assert torch.equal(past[:, 0], x[:, 0])
    assert np.allclose(planner.normalizer.unnormalize(past.numpy())[:, 1:, list(FLAG_COLUMNS)], 0.0)
    in_turn = place_condition(planner, first=4, last=12)(1, 0, obs)(x)
    flags = planner.normalizer.unnormalize(in_turn.numpy())[:, :, list(FLAG_COLUMNS)]
    assert np.allclose(flags[:, 4:12, 1], 1.0) and np.allclose(flags[:, 4:12][:, :, [0, 2, 3]], 0.0)


def test_the_goal_state_ends_each_plan_as_it_started_but_its_block_on_target(planner: RecordingPlanner) -> None:
    """``placed_goal_condition``: plan i's last state is its first with block ``blocks[i]``'s xy at that block's
    target (raw units); every other step is left as it is."""
    x = torch.rand(2, HORIZON, OBS_DIM) * 2 - 1
    y = placed_goal_condition(planner, [2, 0])(x)
    assert torch.equal(y[:, :-1], x[:, :-1])
    raw_first, raw_last = (planner.normalizer.unnormalize(t.numpy()) for t in (x[:, 0], y[:, -1]))
    for row, block in enumerate((2, 0)):
        xy = block_position_columns(block).start + np.arange(2)
        np.testing.assert_allclose(raw_last[row, xy], PLACE_TARGETS[block, :2], atol=1e-6)
        rest = np.setdiff1d(np.arange(OBS_DIM), xy)
        np.testing.assert_allclose(raw_last[row, rest], raw_first[row, rest], atol=1e-6)


def test_pick_and_place_plans_end_on_target_though_their_resting_blocks_are_pinned(
    planner: RecordingPlanner, tmp_path: Path
) -> None:
    """``pick_place.goal_state`` reaches the evaluation's plans and is applied after pinning: a plan that never
    picks its block still ends with it on target (pinning alone would hold it where it rests)."""
    from adaptdiffuser.family_registry import get_family

    settings = {"setups": [1], "episodes": 1, "batch_size": 1, "goal_state": True}
    task = params_from_dict(
        kuka_raw({"diffusion.horizon": HORIZON, "planning.pin_resting_blocks": True, "pick_place": settings}, tmp_path)
    ).resolve("kuka-stacking")
    planner.clear()
    get_family("kuka").evaluate_unseen(task, planner, 1.0, {}, 0, "", False)
    for stretch, plans in enumerate(planner.plans):
        block = stretch % N_BLOCKS  # in_turn
        xy = block_position_columns(block).start + np.arange(2)
        np.testing.assert_allclose(plans[0, -1, xy], PLACE_TARGETS[block, :2], atol=1e-5)
        np.testing.assert_allclose(plans[0, -1, :N_JOINTS], plans[0, 0, :N_JOINTS], atol=1e-5)


def test_a_hold_span_must_be_ordered(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="hold must be"):
        params_from_dict(kuka_raw({"pick_place.hold": [0.75, 0.25]}, tmp_path))


def test_a_hold_span_that_holds_no_step_of_the_plan_is_refused(tmp_path: Path) -> None:
    """The span is cut at whole steps of the horizon: one narrower than a step would hold nothing and silently turn
    every flag off from its start."""
    params_from_dict(kuka_raw({"diffusion.horizon": 32, "pick_place.hold": [0.5, 0.55]}, tmp_path))  # 16 to 17
    with pytest.raises(ConfigError, match=r"pick_place.hold: \[0.5, 0.52\] of a 32-step plan holds no step"):
        params_from_dict(kuka_raw({"diffusion.horizon": 32, "pick_place.hold": [0.5, 0.52]}, tmp_path))


def test_a_flag_the_data_never_turned_on_is_held_at_the_datas_top_not_beyond() -> None:
    """A block the training data never picked (its flag always 0, a zero span): holding it asks for the data's
    highest value, not for 1.0 over a zero span (about 2e6 in the model's units)."""
    never = tiny_planner(flag_high=0.0)
    y = held_block_condition(never, [0], first=2, last=6)(torch.zeros(1, HORIZON, OBS_DIM))
    assert float(y.abs().max()) <= 1.0
    np.testing.assert_allclose(y[0, 2:6, FLAG_COLUMNS[0]].numpy(), 1.0)
