"""Locomotion-style planning pieces on a real simulator: episodes that end on termination, start-conditioned
training, and the value-planning controller that executes the first action of the best of N guided plans."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from conftest import maze_sim
from torch import nn

from adaptdiffuser.checkpoint import make_bundle
from adaptdiffuser.contract import Controller, Simulator, Step
from adaptdiffuser.data.normalizer import GaussianNormalizer
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.diffusion.conditions import training_conditions
from adaptdiffuser.diffusion.guidance import ValueGuidance
from adaptdiffuser.diffusion.samplers import DDIMSampler, DDPMSampler
from adaptdiffuser.evaluation import run_episodes
from adaptdiffuser.families.locomotion.controller import ValuePlanningController, shift_plans
from adaptdiffuser.planning import Planner

CPU = torch.device("cpu")


class FallsAfter(Simulator):
    """A real U-Maze simulator whose episode terminates after a per-instance number of steps."""

    def __init__(self, steps: int) -> None:
        self.env = maze_sim()
        self.steps = steps
        self.obs_dim, self.act_dim, self.state_dim = 4, 2, 4
        self.episode_steps = 20
        self.stepped = 0

    def reset(self, rng):
        self.stepped = 0
        return self.env.reset(rng)

    def step(self, action) -> Step:
        self.stepped += 1
        step = self.env.step(action)
        return Step(step.observation, 1.0, self.stepped >= self.steps)

    def get_state(self):
        return self.env.get_state()

    def set_state(self, state):
        return self.env.set_state(state)


class Zero(Controller):
    def act(self, envs, obs, t):
        return np.zeros((len(envs), 2))


def test_terminated_episodes_stop_and_keep_their_length() -> None:
    lengths = iter([3, 25, 7])  # the second runs into the 20-step limit first
    made = []

    def factory():
        made.append(FallsAfter(next(lengths)))
        return made[-1]

    result = run_episodes(factory, Zero(), 3, seed=0, batch_size=3, progress=False)
    assert result.lengths == [3, 20, 7]
    assert result.terminated == [True, False, True]
    assert result.returns == [3.0, 20.0, 7.0]  # reward 1 per step taken, none after termination
    assert [env.stepped for env in made] == [3, 20, 7]  # a terminated simulator is never stepped again
    assert [len(ex) for ex in result.executed] == [4, 21, 8]
    assert result.goals == [None] * 3


def test_start_conditioning_inpaints_only_the_first_state() -> None:
    x0 = torch.randn(5, 8, 6)
    start = training_conditions("start", x0, act_dim=2)
    both = training_conditions("start_goal", x0, act_dim=2)
    assert list(start) == [0] and sorted(both) == [0, 7]
    torch.testing.assert_close(start[0], x0[:, 0, 2:])


class PreferFirstAction(nn.Module):
    """A stand-in value: the first action's first dimension, so higher means 'push right now'."""

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return x[:, 0, 0]


def _planner(tiny_model_params, tiny_diffusion_params, dtype: torch.dtype = torch.float32) -> Planner:
    torch.manual_seed(0)
    normalizer = GaussianNormalizer(np.zeros(6), np.full(6, 2.0))
    bundle = make_bundle(tiny_model_params, tiny_diffusion_params, 4, 2, normalizer, conditioning="start")
    bundle.ema.to(dtype)
    return Planner(bundle, DDIMSampler(4), CPU)


def test_value_controller_executes_the_first_action_of_the_best_plan(tiny_model_params, tiny_diffusion_params) -> None:
    planner = _planner(tiny_model_params, tiny_diffusion_params)
    guidance = ValueGuidance(PreferFirstAction(), scale=0.0)
    controller = ValuePlanningController(planner, guidance, n_samples=6, seed=12)
    envs = [maze_sim() for _ in range(2)]
    obs = np.stack([env.reset(np.random.default_rng(i)) for i, env in enumerate(envs)])
    controller.begin(envs, obs, [0, 1])
    actions = controller.act(envs, obs, 0)

    # the same samples, drawn directly: per episode the chosen action is the one with the largest value; sample j of
    # episode e is seeded by (seed, e, t, j)
    seeds = [derive_seed(12, e, 0, j) for e in (0, 1) for j in range(6)]
    assert controller.seeds([0, 1], 0) == seeds
    x = planner.sample(np.repeat(obs, 6, axis=0), None, seeds, guidance)
    raw = planner.actions(x).reshape(2, 6, 2)
    best = x[:, 0, 0].reshape(2, 6).argmax(dim=1).numpy()
    np.testing.assert_allclose(actions, raw[np.arange(2), best])
    assert not np.allclose(actions, raw[:, 0])  # not just the first sample
    assert controller.first_plans.shape == (2, tiny_diffusion_params.horizon, 4)
    np.testing.assert_allclose(controller.first_plans[:, 0], obs, atol=1e-5)  # plans start at the observation


def test_value_guidance_raises_the_value_of_the_chosen_plans(tiny_model_params, tiny_diffusion_params) -> None:
    # an untrained epsilon-predicting denoiser returns about its input at the last step, so what guidance did to
    # the noisy plans survives into the samples (an untrained x0-predictor would replace it by its own output)
    eps_params = dataclasses.replace(tiny_diffusion_params, predict_epsilon=True)
    planner = _planner(tiny_model_params, eps_params)
    obs = np.zeros((8, 4))
    plain = ValueGuidance(PreferFirstAction(), scale=0.0)
    guided = ValueGuidance(PreferFirstAction(), scale=5.0, n_guide_steps=2, t_stopgrad=0)
    v_plain = plain.values(planner.sample(obs, None, range(8), plain))
    v_guided = guided.values(planner.sample(obs, None, range(8), guided))
    assert v_guided.mean() > v_plain.mean() + 0.1


class CallLog:
    """Records the diffusion steps and batch sizes of a denoiser network's forward calls."""

    def __init__(self, net: nn.Module) -> None:
        self.calls: list[tuple[int, int]] = []
        net.register_forward_hook(lambda module, args, out: self.calls.append((int(args[1][0]), len(args[0]))))


def test_warm_start_noises_the_guess_and_visits_only_the_steps_below(tiny_model_params, tiny_diffusion_params) -> None:
    planner = _planner(tiny_model_params, tiny_diffusion_params)  # DDIM 4 of 8 steps: 7, 5, 2, 0
    planner.sampler = DDPMSampler()
    log = CallLog(planner.model.model)
    obs = np.zeros((3, 4))
    cold = planner.sample(obs, None, [1, 2, 3])
    assert [t for t, _ in log.calls] == list(range(7, -1, -1))
    log.calls.clear()
    guess = torch.randn_like(cold)
    warm = planner.sample(obs, None, [1, 2, 3], warm_start=(guess, 3))
    assert [t for t, _ in log.calls] == [3, 2, 1, 0]
    torch.testing.assert_close(warm[:, 0, 2:], cold[:, 0, 2:])  # the start is still inpainted
    # the result follows the guess, row by row: the same guess gives the same rows in any batch (compared in
    # float64, where no CPU's choice of kernels by batch size shows; see test_batch_independence)
    other = planner.sample(obs, None, [1, 2, 3], warm_start=(-guess, 3))
    assert not torch.allclose(warm, other)
    exact = _planner(tiny_model_params, tiny_diffusion_params, torch.float64)
    exact.sampler = DDPMSampler()
    batch = exact.sample(obs, None, [1, 2, 3], warm_start=(guess.double(), 3))
    alone = exact.sample(obs[1:2], None, [2], warm_start=(guess[1:2].double(), 3))
    torch.testing.assert_close(alone[0], batch[1], atol=1e-9, rtol=0.0)
    with pytest.raises(ValueError, match="warm start step"):
        planner.sample(obs, None, [1, 2, 3], warm_start=(guess, 8))
    with pytest.raises(ValueError, match="warm start trajectories"):
        planner.sample(obs, None, [1, 2, 3], warm_start=(guess[:2], 3))


def test_warm_started_controller_replans_from_its_last_plan_shifted(tiny_model_params, tiny_diffusion_params) -> None:
    planner = _planner(tiny_model_params, tiny_diffusion_params)
    planner.sampler = DDPMSampler()
    log = CallLog(planner.model.model)
    guidance = ValueGuidance(PreferFirstAction(), scale=0.0)
    controller = ValuePlanningController(planner, guidance, n_samples=3, seed=5, warm_start_step=2)
    envs = [maze_sim() for _ in range(2)]
    obs = np.stack([env.reset(np.random.default_rng(i)) for i, env in enumerate(envs)])
    controller.begin(envs, obs, [0, 1])
    controller.act(envs, obs, 0)
    assert len(log.calls) == 8  # the first decision runs the whole chain
    first = controller.last_plans.clone()
    log.calls.clear()
    actions = controller.act(envs, obs, 1)
    assert [t for t, _ in log.calls] == [2, 1, 0]  # then only the steps from the warm start down

    # the same decision drawn directly from the shifted plans
    guess = shift_plans(first).repeat_interleave(3, dim=0)
    x = planner.sample(np.repeat(obs, 3, axis=0), None, controller.seeds([0, 1], 1), guidance, (guess, 2))
    best = x[:, 0, 0].reshape(2, 3).argmax(dim=1).numpy()
    np.testing.assert_allclose(actions, planner.actions(x).reshape(2, 3, 2)[np.arange(2), best], atol=1e-6)
    torch.testing.assert_close(shift_plans(first)[:, :-1], first[:, 1:])
    with pytest.raises(ValueError, match="warm_start_step"):
        ValuePlanningController(planner, guidance, n_samples=3, seed=5, warm_start_step=8)


class PlansForEveryRow(ValuePlanningController):
    """The controller as it was: plans for ended episodes too."""

    def active_rows(self, n: int) -> np.ndarray:
        return np.ones(n, dtype=bool)


def test_ended_episodes_are_not_planned_for_and_the_others_do_not_change(
    tiny_model_params, tiny_diffusion_params
) -> None:
    planner = _planner(tiny_model_params, tiny_diffusion_params, torch.float64)  # other batch shapes: see below
    log = CallLog(planner.model.model)
    guidance = ValueGuidance(PreferFirstAction(), scale=0.0)

    def run(kind: type[ValuePlanningController]):
        log.calls.clear()
        lengths = iter([3, 25])  # episode 0 ends after 3 steps, episode 1 runs into the 20-step limit
        result = run_episodes(lambda: FallsAfter(next(lengths)), kind(planner, guidance, 2, 1), 2, 0, 2, progress=False)
        return result, [b for t, b in log.calls if t == 7]  # one call per decision at the first DDIM step

    skipping, sizes = run(ValuePlanningController)
    assert sizes == [4, 4, 4] + [2] * 17  # 2 episodes x 2 samples, then only the running one
    assert skipping.lengths == [3, 20]
    every, sizes = run(PlansForEveryRow)
    assert sizes == [4] * 20
    # other batch shapes, compared in float64, where no CPU's kernel choice by batch size shows over 20 steps
    for a, b in zip(skipping.executed, every.executed, strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-9)
