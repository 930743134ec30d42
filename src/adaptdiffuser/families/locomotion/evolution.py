"""Locomotion's evolution phases. Generation: value-guided, start-conditioned plans of one horizon from start
states drawn from the task's dataset (restored from the stored qpos/qvel) and from fresh resets. Discrimination:
each plan's actions are executed from the same full state in the real simulator; a plan is rejected when the
executed observations leave the planned ones by more than ``max_error`` (root mean square over dimensions, in units
of the dataset's per-dimension standard deviation) or when the robot falls; the rest are selected by real reward:
the paper's per-phase thresholds on reward per step x 1000 (its table is on a 1000-step episode scale), or the
generic quantile / top-k rules."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from adaptdiffuser.config import DiscriminateParams, GenerateParams, TaskParams
from adaptdiffuser.contract import Judgement, TaskFiles, TrackedTrajectory
from adaptdiffuser.data.schema import SchemaError, Trajectories, make_metadata, read_trajectories
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.evolution.discriminator import SelectionRule, generic_selection_rule, select
from adaptdiffuser.families.locomotion.params import PAPER_THRESHOLDS, LocomotionTaskParams
from adaptdiffuser.families.locomotion.simulator import LocomotionSimulator

START_COLUMN = "task_start_state"


@dataclass(frozen=True)
class PerStepThresholdRule:
    """Keep segments whose real reward per step x 1000 reaches ``threshold`` (the paper's table's scale)."""

    threshold: float

    def select(self, returns: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        scaled = 1000.0 * np.asarray(returns, dtype=np.float64) / np.maximum(np.asarray(lengths), 1)
        keep = np.flatnonzero(scaled >= self.threshold)
        return keep[np.argsort(-scaled[keep], kind="stable")]


def selection_rule(task_name: str, cfg: DiscriminateParams, phase: int) -> SelectionRule:
    """``paper``: the table's threshold of this task and phase (phase 3 on reuse phase 2's); else the generic rule."""
    if cfg.rule != "paper":
        return generic_selection_rule(cfg)
    if task_name not in PAPER_THRESHOLDS:
        raise ValueError(f"no paper threshold for {task_name!r}; use evolution.discriminate.rule quantile or top_k")
    thresholds = PAPER_THRESHOLDS[task_name]
    return PerStepThresholdRule(thresholds[min(phase, len(thresholds)) - 1])


def sample_start_states(
    sim: LocomotionSimulator, dataset: Trajectories, n: int, reset_fraction: float, rng: np.random.Generator
) -> np.ndarray:
    """``n`` full simulator states ``[n, state_dim]``: ``round(reset_fraction * n)`` fresh resets, the rest drawn
    uniformly from the dataset's non-terminal rows."""
    if dataset.sim_state is None:
        raise SchemaError("the locomotion dataset has no sim_state column; regenerate it with the collect stage")
    n_reset = int(round(reset_fraction * n))
    rows = np.flatnonzero(~dataset.terminal)
    picked = dataset.sim_state[rng.choice(rows, size=n - n_reset, replace=True)]
    resets = []
    for _ in range(n_reset):
        sim.reset(rng)
        resets.append(sim.get_state())
    return np.concatenate([np.asarray(picked, dtype=np.float64), np.reshape(resets, (n_reset, sim.state_dim))])


def generate_segments(
    sim: LocomotionSimulator,
    task: TaskParams[LocomotionTaskParams],
    planner: Any,
    files: TaskFiles,
    cfg: GenerateParams,
    seed: int,
    generator: dict[str, Any],
    progress: bool,
) -> tuple[Trajectories, dict[str, float]]:
    """One value-guided plan per start state (row ``i`` draws its noise from seed ``(seed, i)``), as a dataset of
    planned observations and actions (reward unknown until executed: zero), each row naming its start state."""
    from adaptdiffuser.diffusion.guidance import ValueGuidance
    from adaptdiffuser.value_training import load_value

    rng = np.random.default_rng(seed)
    dataset = read_trajectories(files.dataset, env=task.name)
    starts = sample_start_states(sim, dataset, cfg.tasks, task.settings.evolution.reset_fraction, rng)
    observations = np.stack([sim.set_state(state) for state in starts])
    value_net, _ = load_value(files.value, planner.device)
    g = task.settings.guide
    guidance = ValueGuidance(value_net, g.scale, g.n_guide_steps, g.t_stopgrad, g.scale_grad_by_std)
    plans, values = [], []
    for first in tqdm(range(0, len(starts), cfg.batch_size), desc="generate", disable=not progress):
        rows = range(first, min(first + cfg.batch_size, len(starts)))
        x = planner.sample(observations[list(rows)], None, [derive_seed(seed, i) for i in rows], guidance)
        with torch.no_grad():
            values.append(guidance.values(x).cpu().numpy())
        plans.append(planner.normalizer.unnormalize(x.double().cpu().numpy()))
    plans_arr = np.concatenate(plans)
    act_dim, n, horizon = planner.act_dim, len(starts), plans_arr.shape[1]
    traj = Trajectories(
        episode_id=np.repeat(np.arange(n), horizon),
        step=np.tile(np.arange(horizon), n),
        observation=plans_arr[:, :, act_dim:].reshape(n * horizon, -1).astype(np.float32),
        action=plans_arr[:, :, :act_dim].reshape(n * horizon, -1).astype(np.float32),
        reward=np.zeros(n * horizon, dtype=np.float32),
        terminal=np.zeros(n * horizon, dtype=bool),
        timeout=np.tile(np.arange(horizon) == horizon - 1, n),
        metadata=make_metadata(task.name, sim.obs_dim, act_dim, "synthetic", generator),
        extra={"task_id": np.repeat(np.arange(n), horizon), START_COLUMN: np.repeat(starts, horizon, axis=0)},
    )
    stats = {
        "generated": n,
        "from_dataset": n - int(round(task.settings.evolution.reset_fraction * n)),
        "planned_value_mean": float(np.concatenate(values).mean()),
    }
    return traj, stats


def execute_segment(
    sim: LocomotionSimulator, start_state: np.ndarray, planned_obs: np.ndarray, actions: np.ndarray, scale: np.ndarray
) -> tuple[TrackedTrajectory, np.ndarray, bool]:
    """Execute a plan's actions from ``start_state``: the executed trajectory (observations ``[H]``, the planned
    actions, the error of each executed next observation against the planned one in units of ``scale``, the real
    reward of each of the H actions), the full states before each step ``[H, state_dim]`` and whether it fell."""
    obs = sim.set_state(start_state)
    observations, states, rewards, errors = [obs], [sim.get_state()], [], []
    fell = False
    for t, action in enumerate(actions):
        step = sim.step(action)
        rewards.append(step.reward)
        if t + 1 < len(actions):
            observations.append(step.observation)
            states.append(sim.get_state())
            errors.append(float(np.sqrt(np.mean(np.square((step.observation - planned_obs[t + 1]) / scale)))))
        if step.terminated:
            fell = True
            break
    tracked = TrackedTrajectory(
        observations=np.asarray(observations),
        actions=np.asarray(actions[: len(observations)], dtype=np.float64),
        errors=np.asarray(errors, dtype=np.float64),
        rewards=np.asarray(rewards, dtype=np.float64),
        steps_to_goal=-1,
    )
    return tracked, np.asarray(states), fell


@dataclass
class SegmentJudgement(Judgement):
    """A :class:`Judgement` that also holds the full simulator states of each executed segment."""

    states: list[np.ndarray] | None = None


def judge_segments(
    sim: LocomotionSimulator,
    task: TaskParams[LocomotionTaskParams],
    generated: Trajectories,
    dataset: Trajectories,
    cfg: DiscriminateParams,
    phase: int,
    progress: bool,
) -> SegmentJudgement:
    """Execute every generated segment; reject falls and segments whose error exceeds ``cfg.max_error``; select
    the rest with the rule ``cfg.rule`` names. (Tracking cannot be switched off: the reward of a locomotion plan
    is only known by running it.)"""
    if START_COLUMN not in generated.extra:
        raise SchemaError(f"generated locomotion file lacks column {START_COLUMN!r}")
    if not cfg.tracking:
        raise ValueError("locomotion plans are judged by executing them: evolution.discriminate.tracking must be true")
    scale = np.maximum(dataset.observation.astype(np.float64).std(axis=0), 1e-6)
    judged, states, passed = [], [], []
    for episode in tqdm(generated.episodes(), desc="discriminate", disable=not progress, mininterval=2.0):
        start = np.asarray(generated.extra[START_COLUMN][episode.start], dtype=np.float64)
        planned_obs = generated.observation[episode].astype(np.float64)
        tracked, full_states, fell = execute_segment(
            sim, start, planned_obs, generated.action[episode].astype(np.float64), scale
        )
        judged.append(tracked)
        states.append(full_states)
        passed.append(not fell and tracked.max_error <= cfg.max_error)
    passed_arr = np.asarray(passed, dtype=bool)
    kept = select(judged, np.flatnonzero(passed_arr), selection_rule(task.name, cfg, phase))
    return SegmentJudgement(trajectories=judged, passed_tracking=passed_arr, kept=kept, states=states)


def selected_segments(
    sim: LocomotionSimulator,
    task: TaskParams[LocomotionTaskParams],
    judgement: SegmentJudgement,
    generator: dict[str, Any],
) -> Trajectories:
    """The kept executed segments with their real rewards and full states (none fell, so none is terminal)."""
    kept = [judgement.trajectories[i] for i in judgement.kept]
    lengths = [len(t.observations) for t in kept]
    n = sum(lengths)
    timeout = np.zeros(n, dtype=bool)
    timeout[np.cumsum(lengths) - 1] = True
    return Trajectories(
        episode_id=np.repeat(np.arange(len(kept)), lengths),
        step=np.concatenate([np.arange(k) for k in lengths]),
        observation=np.concatenate([t.observations for t in kept]).astype(np.float32),
        action=np.concatenate([t.actions for t in kept]).astype(np.float32),
        reward=np.concatenate([t.rewards[: len(t.observations)] for t in kept]).astype(np.float32),
        terminal=np.zeros(n, dtype=bool),
        timeout=timeout,
        metadata=make_metadata(task.name, sim.obs_dim, sim.act_dim, "synthetic", generator, sim.state_dim),
        extra={"task_id": np.repeat(np.asarray(judgement.kept, dtype=np.int64), lengths)},
        sim_state=np.concatenate([judgement.states[i] for i in judgement.kept]),
    )
