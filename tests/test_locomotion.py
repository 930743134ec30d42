"""The locomotion family on real MuJoCo: the simulator's state, reward and termination, the D4RL score reference,
and a tiny behaviour run producing valid, deterministic datasets."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from adaptdiffuser.data.schema import read_trajectories, write_trajectories
from adaptdiffuser.families.locomotion.behaviour import (
    BehaviourSettings,
    collect_locomotion_dataset,
    evaluate_policy_returns,
    load_behaviour_policy,
    random_policy,
)
from adaptdiffuser.families.locomotion.reference import REFERENCE_RETURNS, normalized_score
from adaptdiffuser.families.locomotion.simulator import LocomotionSimulator, parse_task_name

ENV_IDS = ["Hopper-v5", "Walker2d-v5", "HalfCheetah-v5"]


@pytest.fixture(scope="module", params=ENV_IDS)
def sim(request: pytest.FixtureRequest) -> LocomotionSimulator:
    return LocomotionSimulator(request.param)


def test_parse_task_name() -> None:
    assert parse_task_name("hopper-medium") == ("Hopper-v5", "medium")
    assert parse_task_name("walker2d-medium-replay") == ("Walker2d-v5", "medium-replay")
    assert parse_task_name("halfcheetah-medium-expert") == ("HalfCheetah-v5", "medium-expert")
    for bad in ("ant-medium", "hopper-expert", "hopper", ""):
        with pytest.raises(ValueError, match="unknown locomotion task"):
            parse_task_name(bad)


def test_dimensions(sim: LocomotionSimulator) -> None:
    expected = {"Hopper-v5": (11, 3, 12), "Walker2d-v5": (17, 6, 18), "HalfCheetah-v5": (17, 6, 18)}
    assert (sim.obs_dim, sim.act_dim, sim.state_dim) == expected[sim.name]
    assert sim.episode_steps == 1000


def test_reward_and_termination_recomputed_from_states(sim: LocomotionSimulator) -> None:
    rng = np.random.default_rng(0)
    sim.reset(rng)
    errors, terminations = [], 0
    for _ in range(400):
        state = sim.get_state()
        action = rng.uniform(-1.5, 1.5, sim.act_dim)  # out of range on purpose: clipped like the env's
        out = sim.step(action)
        next_state = sim.get_state()
        errors.append(abs(out.reward - sim.reward(state, action, next_state)))
        assert out.terminated == sim.terminated(next_state)
        if out.terminated:
            terminations += 1
            sim.reset(rng)
    assert max(errors) < 1e-6
    if sim.name == "HalfCheetah-v5":
        assert terminations == 0
    else:
        assert terminations > 0  # random actions topple Hopper and Walker2d: the termination path is exercised


def test_state_round_trip_replays_exactly(sim: LocomotionSimulator) -> None:
    rng = np.random.default_rng(1)
    obs0 = sim.reset(rng)
    assert sim.get_state().dtype == np.float64 and sim.get_state().shape == (sim.state_dim,)
    actions = rng.uniform(-0.3, 0.3, (40, sim.act_dim))
    for a in actions[:10]:
        sim.step(a)
    saved, saved_obs = sim.get_state(), sim.observation()
    first = [sim.step(a).observation for a in actions[10:]]
    sim.reset(np.random.default_rng(99))  # somewhere else
    assert np.array_equal(sim.set_state(saved), saved_obs)
    assert np.array_equal(sim.get_state(), saved)
    again = [sim.step(a).observation for a in actions[10:]]
    np.testing.assert_array_equal(np.array(first), np.array(again))
    # reset is seeded from the generator
    assert np.array_equal(sim.reset(np.random.default_rng(1)), obs0)


def test_draw(sim: LocomotionSimulator) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(2)
    sim.reset(rng)
    states = [sim.get_state()]
    for _ in range(20):
        sim.step(rng.uniform(-1, 1, sim.act_dim))
        states.append(sim.get_state())
    fig, ax = plt.subplots()
    sim.draw(ax, np.array(states), plan_states=np.array(states[::2]), title="t")
    assert ax.get_title() == "t" and len(ax.lines) >= 2
    plt.close(fig)


def test_normalized_score_constants() -> None:
    assert REFERENCE_RETURNS["hopper"] == (-20.272305, 3234.3)
    assert REFERENCE_RETURNS["walker2d"] == (1.629008, 4592.3)
    assert REFERENCE_RETURNS["halfcheetah"] == (-280.178953, 12135.0)
    for env_id, (low, high) in zip(ENV_IDS, REFERENCE_RETURNS.values(), strict=True):
        assert normalized_score(low, env_id) == pytest.approx(0.0)
        assert normalized_score(high, env_id) == pytest.approx(100.0)
    assert normalized_score(1000.0, "Hopper-v5") == pytest.approx(100 * (1000 + 20.272305) / (3234.3 + 20.272305))
    np.testing.assert_allclose(normalized_score(np.array([-20.272305, 3234.3]), "hopper-medium"), [0.0, 100.0])
    with pytest.raises(ValueError, match="no D4RL reference"):
        normalized_score(0.0, "Ant-v5")


def test_evaluate_policy_returns_is_seeded() -> None:
    sim = LocomotionSimulator("Hopper-v5")
    a = evaluate_policy_returns(random_policy(sim, 0), sim, episodes=3, seed=5)
    b = evaluate_policy_returns(random_policy(sim, 0), "hopper-medium", episodes=3, seed=5)
    assert a.shape == (3,) and np.array_equal(a, b)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("eval_episodes", 0),
        ("seed", -1),
        ("medium_score", math.nan),
        ("rollout_noise", math.inf),
        ("max_train_steps", 0),
        ("algorithm", "dqn"),
        ("unknown_knob", 1),
    ],
)
def test_bad_settings_name_the_field(field: str, value: object) -> None:
    with pytest.raises(ValidationError, match=field):
        BehaviourSettings(**{field: value})


def test_expert_target_below_medium_is_refused() -> None:
    with pytest.raises(ValidationError, match="expert_score"):
        BehaviourSettings(medium_score=50.0, expert_score=40.0)


# -- a tiny behaviour run (target unreachable) ----------------------------------------------------------------

TINY = {
    "max_train_steps": 300,
    "max_expert_steps": 300,
    "learning_starts": 100,
    "eval_every": 150,
    "eval_episodes": 1,
    "dataset_steps": 400,
    "episode_steps": 60,
    "medium_score": 95.0,
    "medium_band": None,  # no band: a tiny budget reaches no real score
    "expert_score": 99.0,
    "batch_size": 50,
    "net_arch": [32, 32],
    "torch_threads": 1,
    "rollout_noise": 0.1,
    "ppo_n_steps": 150,
}


@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[object, Path]]:
    runs = {}
    for key, task, seed in [("medium", "hopper-medium", 3), ("medium_again", "hopper-medium", 3),
                            ("medium_other", "hopper-medium", 4), ("replay", "hopper-medium-replay", 3),
                            ("replay_sac", "hopper-medium-replay", 3)]:  # fmt: skip
        out = tmp_path_factory.mktemp(key)
        algorithm = "sac" if key.endswith("sac") else "ppo"
        settings = BehaviourSettings(seed=seed, algorithm=algorithm, **TINY)
        runs[key] = (collect_locomotion_dataset(task, out, settings), out)
    return runs


def _check_dataset(traj, sim: LocomotionSimulator, episode_steps: int) -> None:
    n = len(traj)
    assert traj.observation.shape == (n, sim.obs_dim) and traj.action.shape == (n, sim.act_dim)
    assert traj.sim_state.shape == (n, sim.state_dim) and traj.sim_state.dtype == np.float64
    assert traj.metadata["state_dim"] == sim.state_dim and traj.metadata["source"] == "expert"
    assert np.all(traj.action >= sim.action_low) and np.all(traj.action <= sim.action_high)
    episodes = traj.episodes()
    assert np.array_equal(np.unique(traj.episode_id), np.arange(len(episodes)))
    for sl in episodes:
        length = sl.stop - sl.start
        assert 1 <= length <= episode_steps
        assert np.array_equal(traj.step[sl], np.arange(length))
        ends = traj.terminal[sl] | traj.timeout[sl]
        assert ends[-1] and not ends[:-1].any(), "an episode ends with exactly one terminal or timeout, last"
        assert not (traj.terminal[sl][-1] and traj.timeout[sl][-1])
        if length == episode_steps:
            assert traj.timeout[sl][-1] or traj.terminal[sl][-1]
    # the recorded state is the state before the step: restoring it gives the observation, and stepping the
    # recorded action there gives the recorded reward and termination
    for i in range(0, n, 7):
        obs = sim.set_state(traj.sim_state[i])
        np.testing.assert_allclose(obs.astype(np.float32), traj.observation[i], rtol=1e-6, atol=1e-6)
        out = sim.step(traj.action[i])
        assert out.reward == pytest.approx(float(traj.reward[i]), rel=1e-5, abs=1e-5)
        assert out.terminated == bool(traj.terminal[i])
        if not (traj.terminal[i] or traj.timeout[i]) and i + 1 < n:
            np.testing.assert_allclose(sim.get_state(), traj.sim_state[i + 1], atol=1e-5)


def test_tiny_medium_dataset_is_valid(tiny_runs, tmp_path: Path) -> None:
    traj, out = tiny_runs["medium"]
    sim = LocomotionSimulator("Hopper-v5")
    assert len(traj) == TINY["dataset_steps"]
    _check_dataset(traj, sim, TINY["episode_steps"])
    assert (traj.terminal | traj.timeout).sum() >= TINY["dataset_steps"] // TINY["episode_steps"]
    summary = json.loads((out / "behaviour.json").read_text())
    assert summary["medium"]["reached"] is False and summary["medium"]["steps"] == TINY["max_train_steps"]
    assert [p["steps"] for p in summary["curve"]] == [150, 300]
    assert all({"steps", "mean_return", "normalized_score"} <= set(p) for p in summary["curve"])
    assert (out / "medium.zip").exists() and not (out / "expert.zip").exists()
    assert load_behaviour_policy(out).predict(traj.observation[0].astype(np.float64))[0].shape == (sim.act_dim,)
    write_trajectories(tmp_path / "d.parquet", traj)
    back = read_trajectories(tmp_path / "d.parquet")
    assert np.array_equal(back.sim_state, traj.sim_state) and back.metadata["generator"]["dataset"] == "medium"


@pytest.mark.parametrize("run", ["replay", "replay_sac"])
def test_tiny_medium_replay_dataset_is_valid(tiny_runs, run: str) -> None:
    traj, _ = tiny_runs[run]
    sim = LocomotionSimulator("Hopper-v5")
    assert len(traj) == TINY["max_train_steps"]  # every transition the learner saw up to the medium point
    _check_dataset(traj, sim, TINY["episode_steps"])
    assert traj.metadata["generator"]["dataset"] == "medium-replay"


def test_tiny_run_is_deterministic_under_the_seed(tiny_runs) -> None:
    a, b, c = tiny_runs["medium"][0], tiny_runs["medium_again"][0], tiny_runs["medium_other"][0]
    for name in ("episode_id", "observation", "action", "reward", "terminal", "timeout", "sim_state"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.metadata == b.metadata  # no wall-clock time in the file: the same seed writes the same bytes
    assert not np.array_equal(a.action, c.action)
    curve_a = json.loads((tiny_runs["medium"][1] / "behaviour.json").read_text())["curve"]
    curve_b = json.loads((tiny_runs["medium_again"][1] / "behaviour.json").read_text())["curve"]
    assert [p["mean_return"] for p in curve_a] == [p["mean_return"] for p in curve_b]
