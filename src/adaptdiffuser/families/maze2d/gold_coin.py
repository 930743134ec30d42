"""The unseen gold-coin task (paper section 5.3.1): reach the maze's goal and pick up a coin on the way.

No expert data ever contains a coin. Plans are steered to the coin by :class:`CoinObjective` guidance; a coin
is picked when the executed position passes within ``radius`` of it, and the task is done when the goal is
reached after the pick. This module holds the fixed evaluation cases, the scoring of executed episodes and the
evaluation of a planner on the task (the family's unseen-task evaluation).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from adaptdiffuser.diffusion.guidance import Objective
from adaptdiffuser.evaluation import normalized_score, run_episodes, standard_error
from adaptdiffuser.families.maze2d.execution import PlannerController
from adaptdiffuser.families.maze2d.simulator import Cell, Maze2D, bfs_distances, shortest_path
from adaptdiffuser.planning import Planner
from adaptdiffuser.plots import save_figure

if TYPE_CHECKING:
    from adaptdiffuser.config import TaskParams
    from adaptdiffuser.families.maze2d.params import Maze2DTaskParams

#: where the coin lies relative to the shortest start -> goal path
COIN_KINDS = ("on_path", "off_path", "behind_start")
#: the paper's figure: Medium maze, coin at cell (4, 2) (row, column of the layout), start in the top-left room
PAPER_MEDIUM_CASE = {"start": (1, 1), "coin": (4, 2)}


class CoinObjective(Objective):
    """``J = -sum_t ||xy_t - coin||_2``: the closer the whole plan passes to its coin, the higher. ``coins`` is
    ``[batch, 2]`` (one coin per plan) in maze coordinates. The paper writes the objective as the distance
    ``sum_t ||s_t - s_c||_2`` and, for the Diffuser baseline, uses negative scales ({-50, -100, -200}); J is the
    negative of that distance, so the paper's ``alpha = -50`` on the distance is our ``alpha = 50``."""

    def __init__(self, coins: torch.Tensor, eps: float = 1e-6) -> None:
        self.coins = coins
        self.eps = eps

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        delta = states[..., :2] - self.coins.to(states)[:, None, :]
        return -torch.sqrt((delta**2).sum(-1) + self.eps**2).sum(-1)


@dataclass
class CoinCases:
    """Fixed evaluation cases: start states ``[n, 4]``, coin positions ``[n, 2]`` and the kind of each case."""

    starts: np.ndarray
    coins: np.ndarray
    kinds: list[str]
    start_cells: list[Cell]
    coin_cells: list[Cell]

    def __len__(self) -> int:
        return len(self.starts)


def coin_kind(env: Maze2D, start: Cell, coin: Cell) -> str | None:
    """``on_path`` (strictly between start and goal on a shortest path), ``behind_start`` (reaching the coin from
    the start leads away from the goal and the way back passes the start), ``off_path`` (any other detour), or
    ``None`` when the coin is on the start or goal cell."""
    goal = env.goal_cell
    if coin in (start, goal):
        return None
    if coin in shortest_path(env.layout, start, goal)[1:-1]:
        return "on_path"
    to_goal = bfs_distances(env.layout, goal)
    from_start = bfs_distances(env.layout, start)
    if to_goal[coin] == from_start[coin] + to_goal[start]:
        return "behind_start"
    return "off_path"


def coin_cases(env: Maze2D, per_kind: int, rng: np.random.Generator) -> CoinCases:
    """``per_kind`` cases of each kind the maze allows (U-Maze is a corridor: it has no ``off_path`` case),
    drawn from ``rng``; the Medium maze also gets the paper's case. Starts are cell centres plus the protocol's
    reset noise; coins sit at cell centres."""
    if per_kind <= 0:
        raise ValueError(f"cases per kind must be positive, got {per_kind}")
    free = [tuple(c) for c in env.layout.free_cells]
    pairs: dict[str, list[tuple[Cell, Cell]]] = {kind: [] for kind in COIN_KINDS}
    for start in free:
        if start == env.goal_cell:
            continue
        for coin in free:
            kind = coin_kind(env, start, coin)
            if kind is not None:
                pairs[kind].append((start, coin))
    chosen: list[tuple[str, Cell, Cell]] = []
    for kind in COIN_KINDS:
        if pairs[kind]:
            for i in rng.choice(len(pairs[kind]), size=per_kind, replace=len(pairs[kind]) < per_kind):
                chosen.append((kind, *pairs[kind][i]))
    if env.name == "medium":
        start, coin = PAPER_MEDIUM_CASE["start"], PAPER_MEDIUM_CASE["coin"]
        chosen.append((coin_kind(env, start, coin) or "off_path", start, coin))
    noise = rng.uniform(-env.reset_pos_noise, env.reset_pos_noise, size=(len(chosen), 2))
    velocity = rng.normal(0.0, env.reset_vel_noise, size=(len(chosen), 2))
    starts = np.stack([env.cell_to_xy(s) for _, s, _ in chosen]) + noise
    return CoinCases(
        starts=np.concatenate([starts, velocity], axis=1),
        coins=np.stack([env.cell_to_xy(c) for _, _, c in chosen]),
        kinds=[k for k, _, _ in chosen],
        start_cells=[s for _, s, _ in chosen],
        coin_cells=[c for _, _, c in chosen],
    )


@dataclass
class CoinOutcome:
    """One executed coin episode: the first step within the pick radius (-1 if never), the first step at the
    goal after that (-1 if never), the first step at the goal at all, and whether the plan crossed a wall."""

    pick_step: int
    goal_after_pick_step: int
    goal_step: int
    plan_collides: bool

    @property
    def picked(self) -> bool:
        return self.pick_step >= 0

    @property
    def both(self) -> bool:
        return self.goal_after_pick_step >= 0


def coin_outcome(env: Maze2D, executed: np.ndarray, coin: np.ndarray, radius: float, plan: np.ndarray) -> CoinOutcome:
    """Score one episode from its executed states ``[T + 1, obs]`` (the goal is ``env``'s), the ``coin`` position
    and the planned states ``plan`` (for wall collisions)."""
    near = np.flatnonzero(np.linalg.norm(executed[:, :2] - coin[None, :2], axis=1) <= radius)
    pick = int(near[0]) if len(near) else -1
    at_goal = np.flatnonzero([env.reward(s) > 0 for s in executed])
    after = at_goal[at_goal >= pick] if pick >= 0 else np.zeros(0, dtype=int)
    return CoinOutcome(
        pick_step=pick,
        goal_after_pick_step=int(after[0]) if len(after) else -1,
        goal_step=int(at_goal[0]) if len(at_goal) else -1,
        plan_collides=bool(any(env.in_wall(p[:2]) for p in plan)),
    )


def summarize_coin(outcomes: list[CoinOutcome], kinds: list[str], scores: np.ndarray) -> dict:
    """``gold_coin`` metrics: rates over all cases (with the standard error of the both-rate), the mean score with
    its standard error, and the both-rate of each kind of case."""
    both = np.array([o.both for o in outcomes], dtype=np.float64)
    steps = [o.goal_after_pick_step for o in outcomes if o.both]
    summary = {
        "pick_rate": float(np.mean([o.picked for o in outcomes])),
        "goal_rate": float(np.mean([o.goal_step >= 0 for o in outcomes])),
        "both_rate": float(both.mean()),
        "both_rate_stderr": standard_error(both),
        "collision_rate": float(np.mean([o.plan_collides for o in outcomes])),
        "steps_to_goal_mean": float(np.mean(steps)) if steps else None,  # no case reached both
        "score_mean": float(np.mean(scores)),
        "score_stderr": standard_error(scores),
        "n_episodes": len(outcomes),
    }
    for kind in COIN_KINDS:
        mask = np.array([k == kind for k in kinds])
        if mask.any():
            summary[f"both_rate_{kind}"] = float(both[mask].mean())
    return summary


def save_coin_picture(
    env: Maze2D,
    path: str | Path,
    plain_plan: np.ndarray,
    coin_plan: np.ndarray,
    executed: np.ndarray,
    coin: np.ndarray,
    radius: float,
    title: str,
) -> None:
    """One PNG, two panels like the paper's gold-coin figure: the plan without the coin, and the guided plan
    toward the coin with its execution (``env`` draws the maze)."""
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    fig, (left, right) = plt.subplots(1, 2, figsize=(7, 3.6))
    env.draw(left, plan=plain_plan, executed=None)
    left.plot(*plain_plan[0, :2], "o", color="tab:green", ms=8, label="start")
    left.set_title("without coin", fontsize=9)
    env.draw(right, plan=coin_plan, executed=executed)
    right.set_title("with coin guidance", fontsize=9)
    for ax in (left, right):
        ax.add_patch(Circle(tuple(coin[:2]), radius, color="gold", alpha=0.5))
        ax.plot(*coin[:2], "*", color="darkgoldenrod", ms=14, label="coin")
        ax.legend(loc="lower right", fontsize=6)
    fig.suptitle(title, fontsize=9)
    save_figure(fig, path)


def evaluate_gold_coin(
    make_env: Callable[[], Maze2D],
    task: TaskParams[Maze2DTaskParams],
    planner: Planner,
    alpha: float,
    ref: dict,
    pictures: Path,
    title: str,
    progress: bool,
) -> dict[str, float]:
    """Plan each fixed coin case of ``task`` once, guided toward its coin with scale ``alpha``, follow the plan for a
    whole episode, and score pick / goal / both rates, plan collisions and the navigation score (``ref``: the
    task's score reference); the first ``gold_coin.pictures`` cases are drawn under ``pictures``."""
    gc, replan_every = task.settings.gold_coin, task.planner.replan_every
    env = make_env()
    cases = coin_cases(env, gc.cases_per_kind, np.random.default_rng(gc.seed))
    coins = torch.as_tensor(cases.coins, dtype=torch.float32, device=planner.device)

    def guidance_for(episodes: list[int]):
        return planner.guidance(CoinObjective(coins[episodes]), alpha)

    controller = PlannerController(planner, gc.seed, replan_every, guidance_for=guidance_for)
    result = run_episodes(
        make_env,
        controller,
        len(cases),
        gc.seed,
        gc.batch_size,
        desc=f"gold coin {title}",
        progress=progress,
        reset=lambda e, i: e.set_state(cases.starts[i]),
    )
    outcomes = [
        coin_outcome(env, executed, coin, gc.radius, plan)
        for executed, coin, plan in zip(result.executed, cases.coins, result.plans, strict=True)
    ]
    scores = normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"])
    gold = summarize_coin(outcomes, cases.kinds, scores)
    goals = np.stack([env.goal_state()] * len(cases))
    picked = list(range(min(gc.pictures, len(cases))))
    if picked:
        # the unguided plans on the same noise as the guided first plans (each case's seed at t = 0)
        seeds = controller.seeds(picked, 0)
        plain = planner.plan(cases.starts[picked], goals[picked], seeds)[:, :, planner.act_dim :]
    for i in picked:
        verdict = "picked + goal" if outcomes[i].both else ("picked" if outcomes[i].picked else "missed")
        save_coin_picture(
            env,
            pictures / f"coin_{i:02d}.png",
            plain[i],
            result.plans[i],
            result.executed[i],
            cases.coins[i],
            gc.radius,
            f"{title}, {cases.kinds[i]} coin, alpha {alpha:g}: {verdict}",
        )
    return gold
