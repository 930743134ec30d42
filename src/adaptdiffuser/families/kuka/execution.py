"""Executing KUKA plans: open-loop plans of states replanned a fixed number of times per episode, and the
pick-and-place guidance."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

from adaptdiffuser.contract import Controller
from adaptdiffuser.derived_seeds import derive_seed
from adaptdiffuser.diffusion.conditions import Projection
from adaptdiffuser.diffusion.guidance import GuidanceBase, Objective
from adaptdiffuser.families.kuka.scene import (
    BLOCK_HALF,
    FLAG_COLUMNS,
    N_BLOCKS,
    N_JOINTS,
    OBS_DIM,
    KukaScene,
    block_position_columns,
    covered_blocks,
)
from adaptdiffuser.families.kuka.tasks import PLACE_TARGETS, block_positions, placed_blocks

if TYPE_CHECKING:
    from adaptdiffuser.config import TaskParams
    from adaptdiffuser.families.kuka.params import KukaTaskParams
    from adaptdiffuser.planning import Planner


def plan_commands(plan_states: np.ndarray) -> np.ndarray:
    """The commands ``[..., 11]`` (7 joint targets, 4 suction flags) that reach planned states ``[..., 39]``."""
    return np.concatenate([plan_states[..., :N_JOINTS], plan_states[..., list(FLAG_COLUMNS)]], axis=-1)


def held_block(state: np.ndarray) -> int | None:
    """The block a state ``[39]`` holds: the one whose flag is highest, if that flag is on (> 0.5); else None."""
    flags = state[list(FLAG_COLUMNS)]
    return int(np.argmax(flags)) if flags.max() > 0.5 else None


def commands_following_blocks(scenes: Sequence[KukaScene], obs: np.ndarray, planned: np.ndarray) -> np.ndarray:
    """The commands ``[n, 11]`` toward planned states ``[n, 39]`` from observations ``[n, 39]`` when the arm follows
    the blocks (``planning.follow_blocks``): where a planned state holds block ``b`` (:func:`held_block`),
    the joints come from inverse kinematics, putting the cup on the real block's top until the cup holds ``b``, then
    where the plan carries ``b`` (at the offset the cup really holds it by); elsewhere, and while ``b`` has another
    block on it, the planned joints."""
    commands = plan_commands(planned)
    top = np.array([0.0, 0.0, BLOCK_HALF[2]])
    for i, (scene, o, s) in enumerate(zip(scenes, obs, planned, strict=True)):
        b = held_block(s)
        if b is None:
            continue
        where = block_position_columns(b)
        held = o[FLAG_COLUMNS[b]] > 0.5
        if not held and covered_blocks(block_positions(o))[b]:
            continue
        # held: carry it where the plan does; not yet held: go to where it really is
        target = s[where] + (scene.cup()[0] - o[where]) if held else o[where] + top
        commands[i, :N_JOINTS] = scene.inverse_kinematics(target, rest=s[:N_JOINTS])
    return commands


class PlaceObjective(Objective):
    """``J = -sum_{t >= first} ||xy of block b_i at t - its target||``: plan ``i`` carries block ``blocks[i]`` to
    its pick-and-place target over the plan's steps from ``first`` on."""

    def __init__(self, blocks: Sequence[int], first: int) -> None:
        self.first = first
        self.columns = torch.tensor([block_position_columns(b).start for b in blocks])
        self.targets = torch.as_tensor(PLACE_TARGETS[list(blocks), :2], dtype=torch.float32)

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        tail = states[:, self.first :, :]
        columns = self.columns.to(states.device)
        index = torch.stack([columns, columns + 1], dim=1)[:, None, :].expand(-1, tail.shape[1], -1)
        delta = torch.gather(tail, 2, index) - self.targets.to(states)[:, None, :]
        return -torch.sqrt((delta**2).sum(-1) + 1e-12).sum(-1)


def resting_blocks_pinned(planner: Planner) -> Projection:
    """The plan's blocks rest where they really are until the plan picks them up: for each block, every planned step
    before the block's suction flag first turns on (> 0.5) gets the block's pose (xyz and quaternion) of the plan's
    first step, the real one (inpainted). Works on ``planner``'s normalized trajectories."""
    act, normalizer = planner.act_dim, planner.normalizer
    flags = [act + c for c in FLAG_COLUMNS]
    half = np.zeros((1, act + OBS_DIM))
    half[0, flags] = 0.5
    device = planner.device
    threshold = torch.as_tensor(normalizer.normalize(half)[0, flags], dtype=planner.dtype, device=device)
    # each block's xyz and quaternion: the 7 columns from its position's first
    poses = [torch.arange(7, device=device) + act + block_position_columns(b).start for b in range(N_BLOCKS)]
    flag_index = torch.tensor(flags, device=device)

    def project(x: torch.Tensor) -> torch.Tensor:
        on = x[:, :, flag_index] > threshold  # [batch, horizon, blocks]
        resting = torch.cummax(on.to(torch.int8), dim=1).values == 0  # before the flag's first step on
        x = x.clone()
        for b, cols in enumerate(poses):
            x[:, :, cols] = torch.where(resting[:, :, b : b + 1], x[:, :1, cols], x[:, :, cols])
        return x

    return project


def held_block_condition(planner: Planner, blocks: Sequence[int], first: int, last: int) -> Projection:
    """Plan ``i`` picks block ``blocks[i]`` over steps ``first`` to ``last - 1`` and lets go at ``last``: that
    block's suction flag on and the other blocks' off over those steps, every flag off from ``last`` on (inpainted
    at every denoising step, as the start state is). Step 0, the real start, is never changed. Works on
    ``planner``'s normalized trajectories; a value outside the training data's range is clipped to it."""
    first, last = max(1, first), max(1, last)
    act, normalizer = planner.act_dim, planner.normalizer
    flags = [act + c for c in FLAG_COLUMNS]
    rows = np.zeros((len(blocks) + 1, act + OBS_DIM))  # one row per plan, then all flags off
    rows[np.arange(len(blocks)), [flags[b] for b in blocks]] = 1.0
    # clipped to the data's range: a flag the data never turned on (a tower's base block, never picked) would
    # normalize to about 1e6 over its zero span and wreck the whole plan; clipped, the model holds what it can
    normalized = np.clip(normalizer.normalize(rows)[:, flags], -1.0, 1.0)
    values = torch.as_tensor(normalized, dtype=planner.dtype, device=planner.device)
    holding, off = values[:-1, None, :], values[-1]
    flag_index = torch.tensor(flags, device=planner.device)

    def project(x: torch.Tensor) -> torch.Tensor:
        x = x.clone()
        x[:, first:last, flag_index] = holding
        x[:, last:, flag_index] = off
        return x

    return project


def placed_goal_condition(planner: Planner, blocks: Sequence[int]) -> Projection:
    """Plan ``i`` ends where it started but for block ``blocks[i]``, whose xy is at its pick-and-place target: the
    last planned state is the plan's first (the real start, inpainted) with that block's xy replaced (inpainted at
    every denoising step, as the start is). Works on ``planner``'s normalized trajectories."""
    act, normalizer = planner.act_dim, planner.normalizer
    # each plan's block xy: its two columns in the trajectory, and their target in the model's units
    xy = np.array([[act + block_position_columns(b).start + k for k in range(2)] for b in blocks])
    plans = np.arange(len(blocks))[:, None]
    rows = np.zeros((len(blocks), act + OBS_DIM))
    rows[plans, xy] = PLACE_TARGETS[list(blocks), :2]
    targets = torch.as_tensor(normalizer.normalize(rows)[plans, xy], dtype=planner.dtype, device=planner.device)
    index = torch.as_tensor(xy - act, device=planner.device)  # within a state's columns

    def project(x: torch.Tensor) -> torch.Tensor:
        x = x.clone()
        x[:, -1, act:] = x[:, 0, act:].scatter(1, index, targets.to(x.dtype))
        return x

    return project


class ReplanningController(Controller):
    """Plans ``horizon`` states from the current observation and executes them open loop, one planned state per
    step; replans every ``replan_every`` steps (default ``horizon - 1``, the whole plan, so ``replans`` plans fill an
    episode). Plan ``r`` of episode ``e`` is seeded by ``(seed, e, r)``; ``guidance(k, o, obs)`` gives the guidance
    of a plan drawn ``o`` steps into the ``k``-th stretch of ``horizon - 1`` steps from observations ``obs``
    ``[n, 39]`` (or None); each plan is constrained by ``project`` (e.g. :func:`resting_blocks_pinned`) when given,
    after ``condition(k, o, obs)`` (e.g. :func:`held_block_condition`, or None) when that is given, and then by
    ``finish(k, o, obs)`` (e.g. :func:`placed_goal_condition`: last, so that pinning cannot undo it); with
    ``follow_blocks`` the arm is commanded by :func:`commands_following_blocks` instead of the planned joints. With
    ``record``, :attr:`recorded` collects each episode's planned states ``[T + 1, 39]`` (the start, then the state
    each step was commanded to reach), episodes in the order they ran."""

    def __init__(
        self,
        planner,
        seed: int,
        guidance: Callable[[int, int, int], GuidanceBase | None] | None = None,
        record: bool = False,
        project: Projection | None = None,
        replan_every: int | None = None,
        follow_blocks: bool = False,
        condition: Callable[[int, int, np.ndarray], Projection | None] | None = None,
        finish: Callable[[int, int, np.ndarray], Projection | None] | None = None,
    ) -> None:
        self.planner = planner
        self.seed = seed
        self.guidance = guidance
        self.span = planner.horizon - 1
        self.every = self.span if replan_every is None else replan_every
        if not 0 < self.every <= self.span:
            raise ValueError(f"replan_every must be in [1, {self.span}] (horizon - 1), got {replan_every}")
        self.project = project
        self.condition = condition
        self.finish = finish
        self.follow_blocks = follow_blocks
        self.record = record
        self._rows: list[list[np.ndarray]] = []

    @property
    def recorded(self) -> list[np.ndarray]:
        """Each recorded episode's start and commanded states ``[steps + 1, 39]``, in the order they ran."""
        return [np.stack(rows) for rows in self._rows]

    def begin(self, envs, obs, episodes):
        self.episodes = list(episodes)
        self.first_plans = None
        self.plans: np.ndarray | None = None
        if self.record:
            self.batch_start = len(self._rows)
            self._rows.extend([o.copy()] for o in obs)

    def act(self, envs, obs, t):
        step, replan = t % self.every, t // self.every
        if step == 0:
            seeds = [derive_seed(self.seed, e, replan) for e in self.episodes]
            stretch, offset = divmod(t, self.span)
            guidance = self.guidance(stretch, offset, obs) if self.guidance is not None else None
            condition = self.condition(stretch, offset, obs) if self.condition is not None else None
            finish = self.finish(stretch, offset, obs) if self.finish is not None else None
            project = _then(_then(condition, self.project), finish)
            self.plans = self.planner.plan(obs, None, seeds, guidance, project)[:, :, self.planner.act_dim :]
            if self.first_plans is None:
                self.first_plans = self.plans.copy()
        commanded = self.plans[:, step + 1]
        if self.record:
            for i, state in enumerate(commanded):
                self._rows[self.batch_start + i].append(state.copy())
        if self.follow_blocks:
            return commands_following_blocks([env.scene for env in envs], obs, commanded)
        return plan_commands(commanded)


def _then(first: Projection | None, second: Projection | None) -> Projection | None:
    """``second`` applied after ``first`` (either may be None)."""
    if first is None or second is None:
        return first or second
    return lambda x: second(first(x))


def block_to_place(obs: np.ndarray) -> int:
    """The block pick-and-place moves next from observation ``[39]`` (``pick_place.next_block: free``): the one the
    cup holds; else the lowest-numbered block off its target (:func:`placed_blocks`) with no block on it; else (none
    left) the lowest-numbered block off its target, or block 0."""
    held = held_block(obs)
    if held is not None:
        return held
    off = ~placed_blocks(obs)
    free = off & ~covered_blocks(block_positions(obs))
    candidates = np.flatnonzero(free) if free.any() else np.flatnonzero(off)
    return int(candidates[0]) if len(candidates) else 0


def guided_blocks(next_block: str, stretch: int, obs: np.ndarray) -> list[int]:
    """The block each episode's plan of stretch ``stretch`` is guided to move, from observations ``obs`` ``[n, 39]``:
    ``stretch mod 4`` (``next_block`` ``in_turn``) or each episode's :func:`block_to_place` (``free``)."""
    if next_block == "free":
        return [block_to_place(o) for o in obs]
    return [stretch % N_BLOCKS] * len(obs)


def place_guidance(
    planner: Planner, alpha: float, first: int, next_block: str = "in_turn", on: str = "mean"
) -> Callable[[int, int, np.ndarray], GuidanceBase]:
    """Pick-and-place guidance: the plans of stretch ``k`` pull a block toward its target with scale ``alpha`` over
    the stretch's steps from ``first`` on (a plan drawn ``o`` steps into the stretch: its steps from ``first - o``);
    the block is each episode's :func:`guided_blocks` by ``next_block``; ``on`` says where the guidance acts
    (:class:`~adaptdiffuser.diffusion.guidance.Guidance`)."""
    if next_block not in ("in_turn", "free"):
        raise ValueError(f"next_block must be 'in_turn' or 'free', got {next_block!r}")

    def make(stretch: int, offset: int, obs: np.ndarray) -> GuidanceBase:
        blocks = guided_blocks(next_block, stretch, obs)
        return planner.guidance(PlaceObjective(blocks, max(0, first - offset)), alpha, on)

    return make


def place_condition(
    planner: Planner, first: int, last: int, next_block: str = "in_turn"
) -> Callable[[int, int, np.ndarray], Projection]:
    """Pick-and-place conditioning: the plans of stretch ``k`` hold each episode's :func:`guided_blocks` block over
    the stretch's steps ``first`` to ``last - 1`` and let go at ``last`` (:func:`held_block_condition`; a plan drawn
    ``o`` steps into the stretch: its steps ``first - o`` to ``last - o``)."""

    def make(stretch: int, offset: int, obs: np.ndarray) -> Projection:
        blocks = guided_blocks(next_block, stretch, obs)
        return held_block_condition(planner, blocks, max(0, first - offset), max(0, last - offset))

    return make


def place_goal(planner: Planner, next_block: str = "in_turn") -> Callable[[int, int, np.ndarray], Projection]:
    """Pick-and-place's end condition: the plans of stretch ``k`` end with each episode's :func:`guided_blocks`
    block at its target and the rest of the scene as the plan starts (:func:`placed_goal_condition`)."""

    def make(stretch: int, offset: int, obs: np.ndarray) -> Projection:
        return placed_goal_condition(planner, guided_blocks(next_block, stretch, obs))

    return make


def task_controller(
    task: TaskParams[KukaTaskParams],
    planner: Planner,
    seed: int,
    guidance: Callable[[int, int, int], GuidanceBase | None] | None = None,
    record: bool = False,
    condition: Callable[[int, int, np.ndarray], Projection | None] | None = None,
    finish: Callable[[int, int, np.ndarray], Projection | None] | None = None,
) -> ReplanningController:
    """The controller of a KUKA task's plans, as its ``planning`` settings say (every evaluation and generation)."""
    p = task.settings.planning
    project = resting_blocks_pinned(planner) if p.pin_resting_blocks else None
    return ReplanningController(
        planner, seed, guidance, record, project, p.replan_every, p.follow_blocks, condition, finish
    )


def pick_place_controller(
    task: TaskParams[KukaTaskParams], planner: Planner, alpha: float, seed: int, record: bool = False
) -> ReplanningController:
    """The controller of pick-and-place episodes (evaluation and generation), as the ``pick_place`` settings say:
    guided with scale ``alpha`` from ``guide_from``, conditioned on holding the guided block over ``hold`` when that
    is set and on the scene the plan should leave when ``goal_state`` is."""
    p = task.settings.pick_place
    horizon = planner.horizon
    guidance = place_guidance(planner, alpha, int(p.guide_from * horizon), p.next_block, p.guide_on)
    steps = p.hold_steps(horizon)
    hold = place_condition(planner, *steps, p.next_block) if steps is not None else None
    goal = place_goal(planner, p.next_block) if p.goal_state else None
    return task_controller(task, planner, seed, guidance, record, hold, goal)
