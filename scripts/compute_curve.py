"""The compute study's curve: evolution's gain against phase-0 training, one point per pretraining length.

Reads the records ``bash scripts/compute_study.sh`` keeps under ``metrics/science/<task>-compute/steps-<n>/`` (the
pipeline's summary, its params, the per-seed task metrics) and writes ``metrics/science/<task>-compute.json`` (one
entry per length: phase 0, phase 1 and its equal-compute control with their intervals over training seeds, the gain
over the control on the seeds' own and held-out start states, per seed too) and its figure
``docs/science/<task>-compute.png``. Run again after any length is added; it reads every recorded length::

    python scripts/compute_curve.py metrics/science/maze2d-umaze-compute
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import yaml

from adaptdiffuser.io import read_json, write_json
from adaptdiffuser.plots import save_figure

RECORD = re.compile(r"steps-([1-9][0-9]*)")
SCORE_KEYS = ("score_mean", "score_ci_low", "score_ci_high")
GAIN_KEYS = ("gain_mean", "gain_ci_low", "gain_ci_high", "win_rate")


def _lookup(tree: dict, key: str) -> Any:
    for part in key.split("."):
        tree = tree[part]
    return tree


def _pick(metrics: dict, keys: tuple[str, ...]) -> dict[str, float]:
    return {key: metrics[key] for key in keys if key in metrics}


def length_entry(record: Path, key: str) -> dict:
    """One recorded length: its steps (checked against the params it ran with), scores and gains."""
    steps = int(RECORD.fullmatch(record.name).group(1))
    params = yaml.safe_load((record / "params.yaml").read_text())
    if _lookup(params, key) != steps:
        raise SystemExit(f"{record}: params.yaml has {key}={_lookup(params, key)}, not the folder's {steps}")
    task = params["evolve"]
    phases = read_json(record / "summary.json", f"summary of {record}")[task]
    phase0, phase1 = phases["phase_0"], phases["phase_1"]
    control, held_out = phase1["control"], phase1.get("held_out", {})
    per_seed = read_json(record / task / "phase1-control.json", f"phase 1's control metrics in {record}")["seeds"]
    return {
        "steps": steps,
        "n_seeds": phase1["n_seeds"],
        "phase_0": _pick(phase0, SCORE_KEYS),
        "phase_1": _pick(phase1, SCORE_KEYS),
        "control": _pick(control, SCORE_KEYS),
        "gain": _pick(phase1, GAIN_KEYS),
        "held_out_gain": _pick(held_out, GAIN_KEYS),
        "kept": phase1["discriminator"]["kept"],
        "per_seed": {
            seed: {
                "phase_0": phase0["per_seed"][seed]["score_mean"],
                "gain": values["gain_mean"],
                "held_out_gain": values.get("held_out", {}).get("gain_mean"),
            }
            for seed, values in per_seed.items()
        },
    }


def curve(study: Path, key: str) -> dict:
    """Every recorded length of ``study``, shortest first."""
    records = sorted(
        (path for path in study.iterdir() if RECORD.fullmatch(path.name) and (path / "summary.json").exists()),
        key=lambda path: int(RECORD.fullmatch(path.name).group(1)),
    )
    if not records:
        raise SystemExit(f"{study}: no recorded length (steps-<n>/summary.json); run scripts/compute_study.sh")
    task = yaml.safe_load((records[0] / "params.yaml").read_text())["evolve"]
    return {
        "task": task,
        "key": key,
        "intervals": "95 %, Student t over the training seeds' means (each seed's own and held-out start states)",
        "lengths": [length_entry(record, key) for record in records],
    }


def save_curve_figure(data: dict, path: Path) -> None:
    """Two panels against pretraining steps: the scores (phase 0, phase 1, control) and the gains with intervals."""
    lengths = data["lengths"]
    steps = [entry["steps"] for entry in lengths]
    fig, (scores, gains) = plt.subplots(1, 2, figsize=(10, 3.8))
    for name, label in (("phase_0", "phase 0"), ("control", "phase 1's control"), ("phase_1", "phase 1")):
        means = [entry[name]["score_mean"] for entry in lengths]
        low = [entry[name].get("score_ci_low", mean) for entry, mean in zip(lengths, means, strict=True)]
        high = [entry[name].get("score_ci_high", mean) for entry, mean in zip(lengths, means, strict=True)]
        scores.plot(steps, means, marker="o", label=label)
        scores.fill_between(steps, low, high, alpha=0.15)
    scores.set_ylabel("normalized score")
    for name, label, shift in (("gain", "own start states", 0.97), ("held_out_gain", "held-out start states", 1.03)):
        points = [(step * shift, entry[name]) for step, entry in zip(steps, lengths, strict=True) if entry[name]]
        if not points:
            continue
        xs, gain = zip(*points, strict=True)
        means = [g["gain_mean"] for g in gain]
        errors = [
            [m - g.get("gain_ci_low", m) for m, g in zip(means, gain, strict=True)],
            [g.get("gain_ci_high", m) - m for m, g in zip(means, gain, strict=True)],
        ]
        gains.errorbar(xs, means, yerr=errors, marker="o", capsize=3, label=label)
    gains.axhline(0.0, color="grey", linewidth=0.8)
    gains.set_ylabel("phase 1 - control")
    for ax in (scores, gains):
        ax.set_xscale("log", base=2)
        ax.set_xticks(steps, [f"{s:,}" for s in steps])
        ax.minorticks_off()
        ax.set_xlabel(f"pretraining steps ({data['key']})")
        ax.legend(fontsize=8)
    n_seeds = sorted({entry["n_seeds"] for entry in lengths})
    fig.suptitle(f"{data['task']}: gain against phase-0 training, {'/'.join(map(str, n_seeds))} seeds, 95 % intervals")
    save_figure(fig, path)


def _interval(block: dict, name: str) -> str:
    """``mean [low, high]``; a gain signed, and bold where its interval excludes zero."""
    mean, low, high = (block.get(f"{name}_{part}") for part in ("mean", "ci_low", "ci_high"))
    sign = "+" if name == "gain" else ""
    text = f"{mean:{sign}.1f} [{low:.1f}, {high:.1f}]" if low is not None else f"{mean:{sign}.1f}"
    return f"**{text}**" if name == "gain" and low is not None and (low > 0 or high < 0) else text


def markdown_table(data: dict) -> str:
    """The curve as the Markdown table the docs print (bold: a gain whose interval excludes zero)."""
    lines = [
        "| pretraining steps | seeds | phase 0 [95 %] | phase 1 [95 %] | control [95 %] | gain, own [95 %] "
        "| gain, held out [95 %] | win rate, own | kept per seed | per seed: phase 0 / gain own / held out |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for entry in data["lengths"]:
        gain, held = entry["gain"], entry["held_out_gain"]
        per_seed = "; ".join(
            f"seed {seed}: {values['phase_0']:.1f} / {values['gain']:+.1f}"
            + (f" / {values['held_out_gain']:+.1f}" if values["held_out_gain"] is not None else "")
            for seed, values in sorted(entry["per_seed"].items(), key=lambda item: int(item[0]))
        )
        cells = [
            f"{entry['steps']:,}".replace(",", " "),
            str(entry["n_seeds"]),
            _interval(entry["phase_0"], "score"),
            _interval(entry["phase_1"], "score"),
            _interval(entry["control"], "score"),
            _interval(gain, "gain"),
            _interval(held, "gain") if held else "",
            f"{gain['win_rate']:.2f}" if "win_rate" in gain else "",
            f"{entry['kept']:.1f}",
            per_seed,
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("study", type=Path, help="metrics/science/<task>-compute: the recorded lengths")
    parser.add_argument("--key", default="pretrain.steps", help="the params key the study varied")
    parser.add_argument("--out", type=Path, help="default: <study>.json")
    parser.add_argument("--figure", type=Path, help="default: docs/science/<study folder name>.png")
    parser.add_argument("--markdown", action="store_true", help="also print the table the docs show")
    args = parser.parse_args(argv)
    data = curve(args.study, args.key)
    out = args.out or args.study.with_suffix(".json")
    figure = args.figure or Path("docs/science") / f"{args.study.name}.png"
    write_json(out, data)
    save_curve_figure(data, figure)
    for entry in data["lengths"]:
        gain, held = entry["gain"], entry["held_out_gain"]
        print(
            f"{entry['steps']:>7} steps: phase 0 {entry['phase_0']['score_mean']:.1f}, gain {gain['gain_mean']:+.1f} "
            f"[{gain.get('gain_ci_low', float('nan')):+.1f}, {gain.get('gain_ci_high', float('nan')):+.1f}]"
            + (f", held out {held['gain_mean']:+.1f}" if held else "")
        )
    print(f"wrote {out} and {figure}")
    if args.markdown:
        print(markdown_table(data), end="")


if __name__ == "__main__":
    sys.exit(main())
