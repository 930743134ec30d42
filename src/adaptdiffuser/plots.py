"""Pictures: a plan and its execution, a training-loss curve, the discriminator's histograms, score by phase."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from adaptdiffuser.io import atomic_path  # noqa: E402

if TYPE_CHECKING:
    from adaptdiffuser.contract import Judgement


def save_plan_picture(
    env: Any,
    path: str | Path,
    plan: np.ndarray | None,
    executed: np.ndarray | None,
    title: str,
    goal: np.ndarray | None = None,
) -> None:
    """One PNG: the task, the planned states and the executed states, drawn by ``env.draw(ax, plan=, executed=,
    goal=)`` (a simulator that pictures its task)."""
    fig, ax = plt.subplots(figsize=(4, 4))
    env.draw(ax, plan=plan, executed=executed, goal=goal)
    ax.set_title(title, fontsize=9)
    ax.legend(loc="lower right", fontsize=6)
    save_figure(fig, path)


def save_loss_curve(history: list[tuple[int, float]], path: str | Path) -> None:
    """One PNG of training loss against step."""
    fig, ax = plt.subplots(figsize=(5, 3))
    steps, losses = zip(*history, strict=True) if history else ((), ())
    ax.plot(steps, losses)
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    save_figure(fig, path)


def save_figure(fig: plt.Figure, path: str | Path) -> None:
    """Write ``fig`` to ``path`` as a PNG, atomically, and close it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)


def save_discriminator_histograms(judgement: Judgement, max_error: float, path: str | Path, title: str) -> None:
    """One PNG, two panels: the worst tracking error of each generated plan (with the rejection threshold),
    and the real return of those that passed tracking, kept ones highlighted."""
    trajectories = judgement.trajectories
    errors = np.array([t.max_error for t in trajectories])
    returns = np.array([t.total_reward for t in trajectories])
    passed = judgement.passed_tracking
    kept = np.zeros(len(trajectories), dtype=bool)
    kept[judgement.kept] = True
    fig, (left, right) = plt.subplots(1, 2, figsize=(8, 3))
    left.hist(errors, bins=30, color="tab:gray")
    left.axvline(max_error, color="tab:red", linestyle="--", label=f"threshold {max_error:g}")
    left.set_xlabel("max tracking error")
    left.set_ylabel("plans")
    left.legend(fontsize=7)
    bins = np.histogram_bin_edges(returns, bins=30)
    right.hist(returns[passed & ~kept], bins=bins, color="tab:gray", label="passed tracking, not kept")
    right.hist(returns[kept], bins=bins, color="tab:green", alpha=0.8, label="kept")
    right.set_xlabel("real return over the plan")
    right.legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    save_figure(fig, path)


def save_score_by_phase(
    phases: list[int],
    means: list[float],
    stderrs: list[float],
    path: str | Path,
    control: tuple[list[int], list[float], list[float]] | None = None,
    seed_points: tuple[list[int], list[float]] | None = None,
    control_seed_points: tuple[list[int], list[float]] | None = None,
    dataset_score: float | None = None,
) -> None:
    """One PNG: normalized score of each phase with standard-error bars (phase 0 is the Diffuser baseline) and,
    when given, each phase's equal-compute control (phase k-1's model trained as long on expert data only), each
    training seed's own score as small dots (``(phase, score)`` pairs) and the expert dataset's mean score as a
    dashed line (does the planner beat its data?)."""
    fig, ax = plt.subplots(figsize=(4.4, 3.2))
    if dataset_score is not None:
        ax.axhline(dataset_score, color="grey", ls="--", lw=1, label=f"dataset ({dataset_score:.1f})")
    _draw_by_phase(ax, phases, means, stderrs, control, seed_points, control_seed_points)
    ax.set_ylabel("normalized score")
    save_figure(fig, path)


def save_panels_by_phase(
    panels: dict[str, tuple[list[int], list[float], list[float], tuple[list[int], list[float], list[float]]]],
    path: str | Path,
    title: str,
) -> None:
    """One PNG, one panel per named measure (e.g. an unseen task's score per setup), on one y scale: ``(phases,
    means, stderrs, control)`` as :func:`save_score_by_phase` draws them, with no seed dots."""
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.2), sharey=True, squeeze=False)
    for ax, (name, (phases, means, stderrs, control)) in zip(axes[0], panels.items(), strict=True):
        _draw_by_phase(ax, phases, means, stderrs, control)
        ax.set_title(name, fontsize=9)
    axes[0][0].set_ylabel("score")
    fig.suptitle(title, fontsize=9, y=1.03)
    save_figure(fig, path)


def _draw_by_phase(
    ax: plt.Axes,
    phases: list[int],
    means: list[float],
    stderrs: list[float],
    control: tuple[list[int], list[float], list[float]] | None = None,
    seed_points: tuple[list[int], list[float]] | None = None,
    control_seed_points: tuple[list[int], list[float]] | None = None,
) -> None:
    """Each phase's mean with standard-error bars, its control's beside it, the seeds' own points as dots."""
    line = ax.errorbar(phases, means, yerr=stderrs, marker="o", capsize=4, label="AdaptDiffuser")
    if seed_points is not None and seed_points[0]:
        ax.plot(*seed_points, ".", color=line[0].get_color(), alpha=0.5, ms=5, label="training seeds")
    if control is not None and control[0]:
        c_phases, c_means, c_stderrs = control
        offset = [p + 0.08 for p in c_phases]  # side by side with the phase's own point
        bars = ax.errorbar(
            offset, c_means, yerr=c_stderrs, marker="s", capsize=4, ls="none", label="control (expert only)"
        )
        if control_seed_points is not None and control_seed_points[0]:
            c_x, c_y = control_seed_points
            ax.plot([p + 0.08 for p in c_x], c_y, ".", color=bars[0].get_color(), alpha=0.5, ms=5)
    if len(ax.get_legend_handles_labels()[0]) > 1:
        ax.legend(fontsize=7)
    ax.set_xticks(phases)
    ax.set_xlabel("phase (0 = Diffuser)")


def save_series_picture(
    path: str | Path, executed: np.ndarray, plan: np.ndarray | None, labels: list[str], title: str
) -> None:
    """One PNG, one panel per label: observation dim ``i`` over the episode, and over the first plan if given."""
    fig, axes = plt.subplots(len(labels), 1, figsize=(6, 2 * len(labels)), sharex=True, squeeze=False)
    for dim, (ax, label) in enumerate(zip(axes[:, 0], labels, strict=True)):
        ax.plot(executed[:, dim], color="tab:blue", lw=1.2, label="executed")
        if plan is not None:
            ax.plot(plan[:, dim], color="tab:orange", ls="--", lw=1.2, label="first plan")
        ax.set_ylabel(label)
    axes[0, 0].set_title(title, fontsize=9)
    axes[0, 0].legend(loc="best", fontsize="small")
    axes[-1, 0].set_xlabel("step")
    save_figure(fig, path)
