"""Pictures: a plan and its execution in the environment, and a training-loss curve."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from adaptdiffuser.envs.base import PlanningEnv  # noqa: E402
from adaptdiffuser.io import atomic_path  # noqa: E402


def save_plan_picture(
    env: PlanningEnv,
    path: str | Path,
    plan: np.ndarray | None,
    executed: np.ndarray | None,
    title: str,
    goal: np.ndarray | None = None,
) -> None:
    """One PNG: the task, the planned states and the executed states."""
    fig, ax = plt.subplots(figsize=(4, 4))
    env.draw(ax, plan=plan, executed=executed, goal=goal)
    ax.set_title(title, fontsize=9)
    ax.legend(loc="lower right", fontsize=6)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)


def save_loss_curve(history: list[tuple[int, float]], path: str | Path) -> None:
    """One PNG of training loss against step."""
    fig, ax = plt.subplots(figsize=(5, 3))
    steps, losses = zip(*history, strict=True) if history else ((), ())
    ax.plot(steps, losses)
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
