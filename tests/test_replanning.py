"""Replanning in Maze2D with the real planner (a tiny diffusion model, inpainting, DDIM) in the real simulator: when
the agent is pushed off its plan, the next replan starts from where it now is and replaces the old plan; without
the replanning option the plan made at t = 0 is followed to the end, pushed or not."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import maze_sim

from adaptdiffuser.checkpoint import make_bundle
from adaptdiffuser.config import DiffusionParams, ModelParams
from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.diffusion.samplers import DDIMSampler
from adaptdiffuser.families.maze2d.execution import PlannerController
from adaptdiffuser.families.maze2d.generation import NavigationTasks
from adaptdiffuser.families.maze2d.rollouts import RolloutBatch
from adaptdiffuser.families.maze2d.simulator import Maze2D
from adaptdiffuser.planning import Planner

ACT = 2
K = 4  # replan every K steps
START = np.array([1.0, 1.0, 0.0, 0.0])  # U-Maze, top-right cell; the goal is the top-left one
PUSHED = np.array([1.0, -1.0, 0.3, -0.2])  # two cells down the corridor, moving


class CountingPlanner(Planner):
    """The real planner, counting its calls."""

    calls = 0

    def plan(self, *args, **kwargs) -> np.ndarray:
        self.calls += 1
        return super().plan(*args, **kwargs)


@pytest.fixture(scope="module")
def planner() -> CountingPlanner:
    """A tiny untrained model: what a plan looks like does not matter here, where it starts and when it is made do."""
    torch.manual_seed(0)
    normalizer = MinMaxNormalizer(low=[-1, -1, -1.5, -1.5, -3, -3], high=[1, 1, 1.5, 1.5, 3, 3])
    bundle = make_bundle(
        ModelParams(dim=8, dim_mults=[1, 2]), DiffusionParams(horizon=16, n_steps=8), 4, ACT, normalizer
    )
    return CountingPlanner(bundle, DDIMSampler(4), torch.device("cpu"))


def _run(controller: PlannerController, env: Maze2D, push: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Follow the controller for K steps from START, push the agent to PUSHED (or not), act once more. Returns the
    plan followed before the push, the plan followed after it, and the action taken at step K."""
    obs = env.set_state(START)[None]
    controller.begin([env], obs, [0])
    for t in range(K):
        obs = env.step(controller.act([env], obs, t)[0]).observation[None]
    before = controller.followers[0].plan_states.copy()
    if push:
        obs = env.set_state(PUSHED)[None]
    action = controller.act([env], obs, K)[0]
    return before, controller.followers[0].plan_states, action


def test_replan_after_a_push_starts_from_the_pushed_state(planner: CountingPlanner) -> None:
    env = maze_sim()
    before, after, action = _run(PlannerController(planner, seed=5, replan_every=K), env, push=True)
    np.testing.assert_allclose(before[0], START, atol=1e-5)
    np.testing.assert_allclose(after[0], PUSHED, atol=1e-5)  # the new plan starts where the agent now is
    assert not np.allclose(after[1:-1], before[1:-1], atol=0.05)  # a new plan, not the old one with its start moved
    np.testing.assert_allclose(after[-1], env.goal_state(), atol=1e-5)  # still to the goal
    np.testing.assert_array_equal(action, env.tracking_action(PUSHED, after[1]))  # and it is the one followed
    # the same replan (same seed and step) without the push starts from the agent's own state: the push made the change
    unpushed_env = maze_sim()
    _, unpushed, _ = _run(PlannerController(planner, seed=5, replan_every=K), unpushed_env, push=False)
    np.testing.assert_allclose(unpushed[0], unpushed_env.get_state(), atol=1e-5)
    assert np.abs(unpushed[0, :2] - PUSHED[:2]).max() > 1.0
    assert not np.allclose(unpushed[1:-1], after[1:-1], atol=0.05)


@pytest.mark.parametrize("push", [True, False], ids=["pushed", "not-pushed"])
def test_without_replanning_the_first_plan_is_kept(planner: CountingPlanner, push: bool) -> None:
    env = maze_sim()
    planner.calls = 0
    before, after, action = _run(PlannerController(planner, seed=5, replan_every=0), env, push=push)
    assert planner.calls == 1  # planned once, at t = 0
    np.testing.assert_array_equal(after, before)
    np.testing.assert_allclose(after[0], START, atol=1e-5)
    here = PUSHED if push else env.get_state()
    np.testing.assert_array_equal(action, env.tracking_action(here, before[K + 1]))  # the old plan's next waypoint


def test_rollouts_replan_from_the_pushed_state(planner: CountingPlanner) -> None:
    """The evolution's closed-loop rollouts replan the same way: from the state the agent is in."""
    tasks = NavigationTasks(
        starts=START[None],
        goals=maze_sim().goal_state()[None],
        start_cells=np.zeros((1, 2)),
        goal_cells=np.zeros((1, 2)),
    )
    batch = RolloutBatch([maze_sim()], planner, tasks, np.array([0]), seed=5, replan_every=K)
    for t in range(K):
        batch.step(t)
    before = batch.followers[0].plan_states.copy()
    batch.obs[0] = batch.envs[0].set_state(PUSHED)
    batch.step(K)
    after = batch.followers[0].plan_states
    np.testing.assert_allclose(before[0], START, atol=1e-5)
    np.testing.assert_allclose(after[0], PUSHED, atol=1e-5)
    assert not np.allclose(after[1:-1], before[1:-1], atol=0.05)
    assert batch.plan_time == K
