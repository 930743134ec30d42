"""KUKA's evolution phases (the reference's recipe). Generation: pick-and-place episodes from random starts of both
setups, each a chain of open-loop plans from phase k-1's model guided toward the targets and executed in the
simulator, so each plan starts where the last one ended; the file holds the planned state of every step.
Discrimination: the plans are executed again from the same start; an episode whose execution ever leaves the plan by
more than ``max_error`` in what it aims at (:func:`tracking_error`: the joints and suction flags, L2, the reference's
1.02; with ``planning.follow_blocks``, the blocks' centres, metres) is rejected (its reward zeroed), and so is one
whose executed states leave the stacking data's range by more than ``selection.max_range_excess`` (ours); the rest
are selected by the blocks placed (the paper: reward > 1.5, at least two of four)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from adaptdiffuser.config import DiscriminateParams, GenerateParams, TaskParams
from adaptdiffuser.contract import Judgement, TrackedTrajectory
from adaptdiffuser.data.schema import SchemaError, Trajectories
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.evaluation import run_episodes
from adaptdiffuser.evolution.discriminator import SelectionRule, generic_selection_rule, passes_tracking, select
from adaptdiffuser.families.kuka.dataset import state_episodes
from adaptdiffuser.families.kuka.execution import (
    commands_following_blocks,
    pick_place_controller,
    plan_commands,
)
from adaptdiffuser.families.kuka.scene import FLAG_COLUMNS, N_JOINTS
from adaptdiffuser.families.kuka.simulator import KukaSimulator
from adaptdiffuser.families.kuka.tasks import block_positions

if TYPE_CHECKING:
    from adaptdiffuser.families.kuka.params import KukaTaskParams

SETUP_COLUMN = "pick_place_setup"
#: the columns the reference's tracking check compares: the joints and the suction flags
JOINTS_AND_FLAGS = [*range(N_JOINTS), *FLAG_COLUMNS]
#: the paper's KUKA rule: keep an episode that placed more than this many blocks
PAPER_MIN_PLACED = 1.5


@dataclass(frozen=True)
class MinReturnRule:
    """Keep returns above ``threshold``, best first."""

    threshold: float

    def select(self, returns: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        returns = np.asarray(returns, dtype=np.float64)
        keep = np.flatnonzero(returns > self.threshold)
        return keep[np.argsort(-returns[keep], kind="stable")]


def selection_rule(cfg: DiscriminateParams) -> SelectionRule:
    """``paper``: more than 1.5 blocks placed; else the generic rule ``cfg.rule`` names."""
    return MinReturnRule(PAPER_MIN_PLACED) if cfg.rule == "paper" else generic_selection_rule(cfg)


def setup_of_tasks(n: int, setups: list[int]) -> np.ndarray:
    """The pick-and-place setup of each of ``n`` generated tasks: equal contiguous shares of ``setups``."""
    return np.asarray(setups)[np.arange(n) * len(setups) // n]


def generate_episodes(
    make_simulator: Any,
    task: TaskParams[KukaTaskParams],
    planner: Any,
    cfg: GenerateParams,
    alpha: float,
    seed: int,
    generator: dict[str, Any],
    progress: bool,
) -> tuple[Trajectories, dict[str, float]]:
    """``cfg.tasks`` pick-and-place episodes guided with scale ``alpha`` (task ``i`` starts from the scene drawn with
    ``(seed, i)`` in setup :func:`setup_of_tasks`), batched by ``cfg.batch_size``. Row ``t`` of an episode is the
    state planned for step ``t`` (row 0: the start); the reward column is zero (unknown until executed)."""
    p = task.settings.pick_place
    setups = setup_of_tasks(cfg.tasks, p.setups)
    plans: list[np.ndarray] = []
    placed: list[float] = []
    for setup in p.setups:
        tasks = np.flatnonzero(setups == setup)
        if not len(tasks):
            continue
        controller = pick_place_controller(task, planner, alpha, derive_seed(seed, setup), record=True)
        offset = int(tasks[0])
        result = run_episodes(
            lambda setup=setup: make_simulator(task, "pick_place", setup),
            controller,
            len(tasks),
            seed,
            cfg.batch_size,
            desc=f"generate setup {setup}",
            progress=progress,
            reset=lambda env, k, offset=offset: env.reset(np.random.default_rng([seed, offset + k])),
        )
        plans.extend(controller.recorded)
        placed.extend(result.returns)
    columns = {"task_id": np.arange(cfg.tasks), SETUP_COLUMN: setups}
    traj = state_episodes(plans, task.name, "synthetic", generator, per_episode=columns)
    return traj, {"generated": cfg.tasks, "placed_mean_while_generating": float(np.mean(placed))}


def tracking_error(executed: np.ndarray, planned: np.ndarray, follow_blocks: bool = False) -> float:
    """How far an executed state ``[39]`` is from the planned one in what the execution aims at: the L2 distance of
    the joints (radians) and suction flags (the reference's check), or, when ``follow_blocks``, the largest distance
    of a block's centre from its planned one (metres). Following sends the arm to where the blocks really are, so
    its joints leave the planned ones by design and its flags turn on only once the cup reaches the real block:
    the plan is held to where it puts the blocks."""
    if follow_blocks:
        return float(np.linalg.norm(block_positions(executed) - block_positions(planned), axis=1).max())
    return float(np.linalg.norm(executed[JOINTS_AND_FLAGS] - planned[JOINTS_AND_FLAGS]))


def execute_plan(sim: KukaSimulator, planned: np.ndarray, follow_blocks: bool = False) -> TrackedTrajectory:
    """Execute planned states ``[T + 1, 39]`` open loop from ``planned[0]`` (by the blocks where ``follow_blocks``,
    as :func:`commands_following_blocks`): the executed observations, each executed state's
    :func:`tracking_error`, and the reward of each step (the change in blocks placed; the first entry, for the
    start, is 0)."""
    obs = sim.set_state(planned[0])
    observations, errors, rewards = [obs], [], [0.0]
    for t in range(1, len(planned)):
        if follow_blocks:
            command = commands_following_blocks([sim.scene], obs[None], planned[t][None])[0]
        else:
            command = plan_commands(planned[t])
        step = sim.step(command)
        obs = step.observation
        observations.append(obs)
        errors.append(tracking_error(obs, planned[t], follow_blocks))
        rewards.append(step.reward)
    return TrackedTrajectory(
        observations=np.asarray(observations),
        actions=np.zeros((len(observations), 0)),
        errors=np.asarray(errors, dtype=np.float64),
        rewards=np.asarray(rewards, dtype=np.float64),
        steps_to_goal=-1,
    )


def within_range(observations: np.ndarray, low: np.ndarray, high: np.ndarray, excess: float | None) -> bool:
    """Whether every state lies within ``[low, high]`` widened by ``excess`` of its width per dimension (always,
    with ``excess`` None)."""
    if excess is None:
        return True
    margin = excess * (high - low)
    return bool(np.all((observations >= low - margin) & (observations <= high + margin)))


def judge_episodes(
    make_simulator: Any,
    task: TaskParams[KukaTaskParams],
    generated: Trajectories,
    cfg: DiscriminateParams,
    expert: np.ndarray,
    max_range_excess: float | None,
    progress: bool,
) -> Judgement:
    """Execute every generated episode in its setup's simulator; reject those whose :func:`tracking_error` exceeds
    ``cfg.max_error`` at some step or whose states leave the range of the ``expert`` states by more than
    ``max_range_excess`` of it (None: no range check); select the rest by blocks placed with the rule
    ``cfg.rule`` names."""
    if SETUP_COLUMN not in generated.extra:
        raise SchemaError(f"generated KUKA file lacks column {SETUP_COLUMN!r}")
    if not cfg.tracking:
        raise ValueError("KUKA plans are judged by executing them: evolution.discriminate.tracking must be true")
    sims: dict[int, KukaSimulator] = {}
    judged = []
    for episode in tqdm(generated.episodes(), desc="discriminate", disable=not progress, mininterval=2.0):
        setup = int(generated.extra[SETUP_COLUMN][episode.start])
        if setup not in sims:
            sims[setup] = make_simulator(task, "pick_place", setup)
        sim, planned = sims[setup], generated.observation[episode].astype(np.float64)
        judged.append(execute_plan(sim, planned, sim.settings.planning.follow_blocks))
    for sim in sims.values():
        sim.close()
    low, high = expert.min(axis=0), expert.max(axis=0)
    tracks = np.array([passes_tracking(t, cfg.max_error) for t in judged], dtype=bool)
    in_range = np.array([within_range(t.observations, low, high, max_range_excess) for t in judged], dtype=bool)
    passed = tracks & in_range
    kept = select(judged, np.flatnonzero(passed), selection_rule(cfg))
    # the report's rejected_tracking counts both checks; these tell them apart (an episode may fail both)
    details = {"off_plan": int((~tracks).sum()), "out_of_range": int((~in_range).sum())}
    return Judgement(trajectories=judged, passed_tracking=passed, kept=kept, details=details)


def selected_episodes(
    task: TaskParams[KukaTaskParams], judgement: Judgement, generator: dict[str, Any]
) -> Trajectories:
    """The kept executed episodes (states only) with their real rewards (the stage never asks with none kept)."""
    kept = [judgement.trajectories[i] for i in judgement.kept]
    return state_episodes(
        [t.observations for t in kept],
        task.name,
        "synthetic",
        generator,
        rewards=[t.rewards for t in kept],
        per_episode={"task_id": np.asarray(judgement.kept, dtype=np.int64)},
    )
