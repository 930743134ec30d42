"""Stage ``report``: per task, score by phase (and its equal-compute control's) as a PNG with error bars and a CSV
table for ``dvc plots show``; a task with an unseen task gets a second PNG of that task's scores by phase."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from adaptdiffuser.intervals import ONE_SEED
from adaptdiffuser.io import atomic_path, read_json
from adaptdiffuser.layout import HELD_OUT, SUMMARY, report_plot_path, score_table_path, unseen_plot_path
from adaptdiffuser.plots import save_panels_by_phase, save_score_by_phase
from adaptdiffuser.stages.common import GAIN_KEYS, phase_entries, unseen_scores

#: ``*_ci_*``: the 95 % interval over training seeds (empty with one seed); ``*_episode_ci_*``: over episodes, the
#: seeds held fixed (the only one a single seed has); ``win_rate``: the share of episodes a phase beats its control
TABLE_COLUMNS = (
    "phase",
    "score_mean",
    "score_stderr",
    "score_ci_low",
    "score_ci_high",
    "control_score_mean",
    "control_score_stderr",
    "control_score_ci_low",
    "control_score_ci_high",
    "gain_mean",
    "gain_stderr",
    "gain_ci_low",
    "gain_ci_high",
    "win_rate",
    "held_out_score_mean",
    "held_out_gain_mean",
    "held_out_gain_ci_low",
    "held_out_gain_ci_high",
    "held_out_win_rate",
    "score_episode_ci_low",
    "score_episode_ci_high",
    "control_score_episode_ci_low",
    "control_score_episode_ci_high",
    "gain_episode_ci_low",
    "gain_episode_ci_high",
    "held_out_gain_episode_ci_low",
    "held_out_gain_episode_ci_high",
    "return_mean",
    "n_episodes",
    "n_seeds",
    "kept",
)
#: the interval keys of a score or gain: over seeds, then over episodes
_BOUNDS = ("ci_low", "ci_high", "episode_ci_low", "episode_ci_high")


def score_table(task_summary: dict) -> list[dict]:
    """One row per phase, in phase order, from one task's entry of ``metrics/summary.json`` (phase 0 has no
    control: its control and gain cells are empty)."""
    rows = []
    for phase, entry in phase_entries(task_summary):
        control, held_out = entry.get("control", {}), entry.get(HELD_OUT, {})
        rows.append(
            {
                "phase": phase,
                **{k: entry[k] for k in ("score_mean", "score_stderr", "return_mean", "n_episodes")},
                **{f"score_{k}": entry.get(f"score_{k}") for k in _BOUNDS},
                "n_seeds": entry.get("n_seeds", 1),
                "control_score_mean": control.get("score_mean"),
                "control_score_stderr": control.get("score_stderr"),
                **{f"control_score_{k}": control.get(f"score_{k}") for k in _BOUNDS},
                **{k: entry.get(k) for k in GAIN_KEYS},
                "held_out_score_mean": held_out.get("score_mean"),
                **{f"held_out_gain_{k}": held_out.get(f"gain_{k}") for k in ("mean", *_BOUNDS)},
                "held_out_win_rate": held_out.get("win_rate"),
                "kept": entry.get("discriminator", {}).get("kept", 0),
            }
        )
    return rows


def unseen_series(task_summary: dict) -> dict[str, dict[str, list]]:
    """Per score of the task's unseen task (``unseen_task``; e.g. KUKA's ``setup1_score``), its phases, means and
    standard errors, and its controls' (``control_phases``, ...), in phase order; empty without an unseen task.
    A standard error a family does not report reads 0."""
    name = task_summary.get("unseen_task")
    series: dict[str, dict[str, list]] = {}
    if name is None:
        return series
    for phase, entry in phase_entries(task_summary):
        m, c = entry.get(name), entry.get("control", {}).get(name)
        for measure in unseen_scores(m or {}):
            s = series.setdefault(measure, {k: [] for k in ("phases", "means", "stderrs")})
            s["phases"].append(phase)
            s["means"].append(m[f"{measure}_mean"])
            s["stderrs"].append(m.get(f"{measure}_stderr") or 0.0)
            if c is not None:
                for key, value in (
                    ("control_phases", phase),
                    ("control_means", c[f"{measure}_mean"]),
                    ("control_stderrs", c.get(f"{measure}_stderr") or 0.0),
                ):
                    s.setdefault(key, []).append(value)
    return series


def _pm(mean: float | None, stderr: float | None) -> str:
    return "" if mean is None else f"{mean:.1f} ± {stderr or 0.0:.1f}"


def _bounds(row: dict, name: str) -> str:
    """`` [low, high]`` of ``<name>``'s 95 % interval over seeds in ``row``; without one (one seed), its interval
    over episodes labelled ``(one seed: over episodes)``; empty without either."""
    for over, label in (("ci", ""), ("episode_ci", f" ({ONE_SEED})")):
        low, high = row.get(f"{name}_{over}_low"), row.get(f"{name}_{over}_high")
        if low is not None and high is not None:
            return f" [{low:.1f}, {high:.1f}]{label}"
    return ""


def _with_interval(row: dict, name: str) -> str:
    """``mean ± stderr [low, high]`` of ``<name>_*`` in ``row``: the 95 % interval (:func:`_bounds`) beside the
    standard error, where the row holds one."""
    text = _pm(row[f"{name}_mean"], row.get(f"{name}_stderr"))
    return text + _bounds(row, name) if text else text


def _rate(value: float | None) -> str:
    return "" if value is None else f"{value:.2f}"


def _only_phase_0_of(entry: dict, other: dict) -> bool:
    """Whether a task's summary entry holds no phase beyond 0 and its phase 0 is ``other``'s."""
    phases = {key for key in entry if key.startswith("phase_")}
    return phases == {"phase_0"} and entry["phase_0"] == other.get("phase_0")


def merge_summaries(summaries: list[tuple[str, dict]]) -> dict:
    """One summary from several ``(label, summary)``, for tables over several runs, losing no result: a task found
    in one file stays as it is; an entry that holds only the phase 0 another file's entry of that task holds too (the
    non-evolved tasks of a run) gives way to the fuller one; entries of one task that differ otherwise (two recipes,
    two runs) are all kept, each named ``<task> (<label>)``."""
    found: dict[str, list[tuple[str, dict]]] = {}
    for label, summary in summaries:
        for task, entry in summary.items():
            entries = found.setdefault(task, [])
            if any(entry == kept or _only_phase_0_of(entry, kept) for _, kept in entries):
                continue
            entries[:] = [(lbl, kept) for lbl, kept in entries if not _only_phase_0_of(kept, entry)]
            entries.append((label, entry))
    merged: dict = {}
    for task, entries in found.items():
        if len(entries) == 1:
            merged[task] = entries[0][1]
        else:
            merged |= {f"{task} ({label})": entry for label, entry in entries}
    return merged


def gains_table(summary: dict) -> list[str]:
    """A Markdown table of every task's phases in ``metrics/summary.json``: score, control score and the gain over
    the control, each mean ± standard error (over training seeds, or over episodes with one seed) and its 95 %
    interval where the summary holds one (over seeds: a t-interval of the seeds' means; with one seed over episodes,
    labelled so); the win rate (the share of start states on which the phase beats its control); the gain and win
    rate on the held-out start states."""
    lines = [
        "| task | phase | score [95% CI] | control (expert only, same steps) [95% CI] | gain over control [95% CI] "
        "| win rate | held-out gain [95% CI] | held-out win rate | seeds x episodes | kept |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for task, task_summary in summary.items():
        for row in score_table(task_summary):
            held_out = row["held_out_gain_mean"]
            held_out_gain = "" if held_out is None else f"{held_out:.1f}" + _bounds(row, "held_out_gain")
            lines.append(
                f"| {task} | {row['phase']} "
                f"| {_with_interval(row, 'score')} "
                f"| {_with_interval(row, 'control_score')} "
                f"| {_with_interval(row, 'gain')} "
                f"| {_rate(row['win_rate'])} | {held_out_gain} | {_rate(row['held_out_win_rate'])} "
                f"| {row['n_seeds']} x {row['n_episodes']} | {row['kept']:g} |"
            )
    return lines


def _pm_or_mean(mean: float, stderr: float | None) -> str:
    return f"{mean:.1f}" if stderr is None else _pm(mean, stderr)


def unseen_table(summary: dict) -> list[str]:
    """A Markdown table of every task's phases on its family's unseen task (``unseen_task`` in its summary entry),
    one row per score it reports (``score``, and e.g. KUKA's ``setup1_score``): the phase's, its control's and the
    gain over the control. The gain is the summary's ``unseen_gain`` (seed by seed, ± standard error over training
    seeds) where it has one with a standard error; otherwise the difference of the two means, marked ``unpaired``,
    whose standard error treats them as independent. No ``±`` where a family reports no standard error. Empty when
    no task has an unseen task."""
    lines = []
    for task, task_summary in summary.items():
        name = task_summary.get("unseen_task")
        if name is None:
            continue
        for phase, entry in phase_entries(task_summary):
            m, c = entry[name], entry.get("control", {}).get(name)
            for measure in unseen_scores(m):
                key, stderr_key = f"{measure}_mean", f"{measure}_stderr"
                control, gain = "", ""
                if c is not None:
                    control = _pm_or_mean(c[key], c.get(stderr_key))
                    paired = entry.get("unseen_gain", {}).get(measure, {})
                    if paired.get("gain_stderr") is not None:
                        gain = _pm(paired["gain_mean"], paired["gain_stderr"])
                    else:
                        stderrs = (m.get(stderr_key), c.get(stderr_key))
                        stderr = None if None in stderrs else float(np.hypot(*stderrs))
                        gain = _pm_or_mean(m[key] - c[key], stderr) + " (unpaired)"
                lines.append(
                    f"| {task} | {phase} | {name} | {measure} | {_pm_or_mean(m[key], m.get(stderr_key))} | {control} "
                    f"| {gain} |"
                )
    if not lines:
        return []
    header = [
        "| task | phase | unseen task | measure | score | control | gain over control |",
        "|---|---|---|---|---|---|---|",
    ]
    return header + lines


def rescaled_score(score: float, ours: tuple[float, float], theirs: tuple[float, float]) -> float:
    """A normalized score on our ``(R_min, R_max)`` expressed on other constants ``theirs`` (such as D4RL's): the
    same return, normalized again. Differences and standard errors scale by the ratio of the ranges alone
    (:func:`rescaled_difference`)."""
    r_min, r_max = ours
    other_min, other_max = theirs
    return 100.0 * (r_min + score / 100.0 * (r_max - r_min) - other_min) / (other_max - other_min)


def rescaled_difference(difference: float, ours: tuple[float, float], theirs: tuple[float, float]) -> float:
    """A difference of normalized scores (a gain, a standard error) on our constants, on ``theirs``."""
    return difference * (ours[1] - ours[0]) / (theirs[1] - theirs[0])


def _on_constants(
    mean: float | None, stderr: float | None, ours: tuple[float, float], theirs: tuple[float, float], score: bool
) -> str:
    """``mean ± stderr`` of our constants on ``theirs``: a score (``score``) or a difference of scores."""
    if mean is None:
        return ""
    value = rescaled_score(mean, ours, theirs) if score else rescaled_difference(mean, ours, theirs)
    return _pm(value, rescaled_difference(stderr or 0.0, ours, theirs))


def d4rl_table(summary: dict) -> list[str]:
    """A Markdown table of every task whose summary gives D4RL's constants beside ours (``reference``): each phase's
    score, its control's and the gain, read on D4RL's constants (the same returns normalized again; gains and
    standard errors scale by the ratio of the ranges). Empty when no task gives them."""
    lines = []
    for task, task_summary in summary.items():
        ref = task_summary.get("reference", {})
        if "d4rl_r_min" not in ref:
            continue
        ours, theirs = (ref["r_min"], ref["r_max"]), (ref["d4rl_r_min"], ref["d4rl_r_max"])
        for row in score_table(task_summary):
            cells = (
                _on_constants(row["score_mean"], row["score_stderr"], ours, theirs, score=True),
                _on_constants(row["control_score_mean"], row["control_score_stderr"], ours, theirs, score=True),
                _on_constants(row["gain_mean"], row["gain_stderr"], ours, theirs, score=False),
            )
            lines.append(f"| {task} | {row['phase']} | " + " | ".join(cells) + " |")
    if not lines:
        return []
    header = [
        "| task | phase | score on D4RL's constants | control | gain over control |",
        "|---|---|---|---|---|",
    ]
    return header + lines


def seed_points(task_summary: dict) -> dict[str, tuple[list[int], list[float]]]:
    """``(phases, values)`` of every training seed's score and control score, from the summary's ``per_seed``."""
    points: dict[str, tuple[list[int], list[float]]] = {"score_mean": ([], []), "control_score_mean": ([], [])}
    for phase, entry in phase_entries(task_summary):
        for seed_entry in entry.get("per_seed", {}).values():
            for name, (xs, ys) in points.items():
                if name in seed_entry:
                    xs.append(phase)
                    ys.append(seed_entry[name])
    return points


def run_report(root: Path, summary_path: Path | None = None, into: Path | None = None) -> dict[str, list[dict]]:
    """Write ``metrics/report/<task>/score_by_phase.csv`` and ``plots/report/<task>/score_by_phase.png`` (and
    ``unseen_by_phase.png`` for a task with an unseen task) under ``into`` (default ``root``) for every task of
    ``summary_path`` (default the pipeline's ``metrics/summary.json``; a kept summary such as
    ``metrics/science/<task>.json`` draws its figures again)."""
    if summary_path is None:
        summary = read_json(root / SUMMARY, "metrics/summary.json (run the summarize stage)")
    else:
        summary = read_json(summary_path, "the summary to report")
    into = root if into is None else into
    tables = {}
    for task, task_summary in summary.items():
        rows = score_table(task_summary)
        table = into / score_table_path(task)
        table.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(table) as tmp, open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=TABLE_COLUMNS)
            writer.writeheader()
            writer.writerows(rows)
        controls = [r for r in rows if r["control_score_mean"] is not None]
        seeds = seed_points(task_summary)
        save_score_by_phase(
            [r["phase"] for r in rows],
            [r["score_mean"] for r in rows],
            [r["score_stderr"] for r in rows],
            into / report_plot_path(task),
            control=(
                [r["phase"] for r in controls],
                [r["control_score_mean"] for r in controls],
                [r["control_score_stderr"] for r in controls],
            ),
            seed_points=seeds["score_mean"],
            control_seed_points=seeds["control_score_mean"],
            dataset_score=task_summary.get("dataset", {}).get("score_mean"),
        )
        unseen = unseen_series(task_summary)
        if unseen:
            panels = {
                measure: (
                    s["phases"],
                    s["means"],
                    s["stderrs"],
                    (s.get("control_phases", []), s.get("control_means", []), s.get("control_stderrs", [])),
                )
                for measure, s in unseen.items()
            }
            save_panels_by_phase(panels, into / unseen_plot_path(task), f"{task}: {task_summary['unseen_task']}")
        tables[task] = rows
    return tables
