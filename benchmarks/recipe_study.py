"""Training recipes side by side: a task's phase-0 score against training CPU-minutes, per recipe and training seed
(printed, written and drawn, never asserted), to choose a recipe on validation episodes.

A recipe file (YAML) gives each recipe its training steps and the task settings it changes:

    today: {steps: 7000}
    cosine: {steps: 3500, set: {pretrain.lr: 0.001, pretrain.lr_schedule: cosine, pretrain.lr_warmup: 100}}

A recipe with ``extends: NAME`` continues recipe NAME's curve (same ``set``, fewer steps, a constant learning rate)
rather than training from step 0: it starts from NAME's points and its last resume state (a constant-rate curve
keeps it when it finishes), so a longer look at a curve costs only the steps it adds
(``learning_curve.py --extend``):

    diffuser-40000: {steps: 40000, set: {pretrain.lr_schedule: constant}}
    diffuser-80000: {steps: 80000, set: {pretrain.lr_schedule: constant}, extends: diffuser-40000}

For every training seed and recipe, ``learning_curve.py`` runs in a process of its own (each pays its own compile,
as a stage does) and evaluates every ``--every`` steps on validation episodes (``--seed``, never the evaluation
seed). A stopped study goes on where it stopped: finished curves are kept, the unfinished one resumes. Then
``summary.json`` in ``--out-dir`` holds per recipe the final score (mean +- standard error over training seeds, and
per seed) and the training CPU minutes (this process's CPU time, all threads: other work on the machine does not
count, so compare recipes measured on one machine), and ``recipes.png`` draws score against CPU minutes (mean over
seeds).

    python benchmarks/recipe_study.py WORKSPACE --task maze2d-umaze --recipes benchmarks/recipes/maze2d-umaze.yaml
        [--training-seeds 0 1 2] [--every 500] [--episodes 50] [--seed 7] [--out-dir recipe-study] [--quiet]
        [--only RECIPE ...]

A value-guided task (``--task hopper-medium --recipes benchmarks/recipes/hopper-medium.yaml``) trains its value
function in each curve, and the curve's CPU minutes include it (``value.*`` keys of ``set`` change it).

WORKSPACE is a pipeline folder whose task has its dataset and reference (``dvc repro reference@<task>``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from adaptdiffuser.evaluation import standard_error
from adaptdiffuser.io import write_json
from adaptdiffuser.tooling.processes import run_stoppable

HERE = Path(__file__).resolve().parent


Recipes = dict[str, dict[str, Any]]


def load_recipes(path: Path) -> Recipes:
    """``name -> {steps, set}`` from a recipe file; a clear error for a recipe without positive ``steps``."""
    recipes = yaml.safe_load(path.read_text()) or {}
    for name, recipe in recipes.items():
        if not isinstance(recipe, dict) or not isinstance(recipe.get("steps"), int) or recipe["steps"] <= 0:
            raise SystemExit(f"{path}: recipe {name!r} needs a positive integer 'steps'")
        unknown = set(recipe) - {"steps", "set", "extends"}
        if unknown:
            raise SystemExit(f"{path}: recipe {name!r} has unknown keys {sorted(unknown)} (steps, set, extends)")
        if "extends" in recipe:
            shorter = recipes.get(recipe["extends"])
            if not isinstance(shorter, dict) or recipe["extends"] == name:
                raise SystemExit(f"{path}: recipe {name!r} extends {recipe['extends']!r}, not another recipe of it")
            if (shorter.get("set") or {}) != (recipe.get("set") or {}) or shorter.get("steps", 0) >= recipe["steps"]:
                raise SystemExit(f"{path}: recipe {name!r} extends {recipe['extends']!r}, which needs the same 'set' "
                                 "and fewer steps")  # fmt: skip
    return recipes


def select_recipes(recipes: Recipes, names: list[str] | None, path: Path) -> Recipes:
    """The recipes named (all when ``names`` is None), in the file's order; a clear error for a name not in it."""
    if names is None:
        return recipes
    unknown = [name for name in names if name not in recipes]
    if unknown:
        raise SystemExit(f"{path}: no recipe {unknown[0]!r}; its recipes: {sorted(recipes)}")
    return {name: recipe for name, recipe in recipes.items() if name in names}


def curve_path(out_dir: Path, name: str, seed: int) -> Path:
    return out_dir / f"{name}-seed{seed}.jsonl"


def read_curve(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def run_curve(args: argparse.Namespace, name: str, recipe: dict[str, Any], seed: int) -> None:
    """One recipe and training seed through ``learning_curve.py`` (it resumes a stopped curve itself)."""
    out = curve_path(args.out_dir, name, seed)
    if any(point["step"] == recipe["steps"] for point in read_curve(out)):
        return
    command = [sys.executable, str(HERE / "learning_curve.py"), str(args.workspace), "--task", args.task,
               "--steps", str(recipe["steps"]), "--every", str(min(args.every, recipe["steps"])),
               "--seed", str(args.seed), "--episodes", str(args.episodes), "--training-seed", str(seed),
               "--label", f"recipe-{name}", "--out", str(out), "--device", args.device]  # fmt: skip
    if args.quiet:
        command.append("--quiet")
    if "extends" in recipe:  # the shorter curve goes first in the study (it is trained there if it is not done)
        from learning_curve import resume_state_path  # torch and the library: only where a curve extends another

        run_curve(args, recipe["extends"], args.recipes_all[recipe["extends"]], seed)
        variant = f"{args.task}-recipe-{recipe['extends']}"
        command += ["--extend", str(curve_path(args.out_dir, recipe["extends"], seed)),
                    "--extend-state", str(resume_state_path(args.workspace.resolve(), variant, seed))]  # fmt: skip
    for key, value in (recipe.get("set") or {}).items():
        command += ["--set", f"{key}={json.dumps(value)}"]
    print(f"== {name}, training seed {seed}: {recipe['steps']} steps {recipe.get('set') or {}}", flush=True)
    code = run_stoppable(command)  # a stopped study lets its curve write its resume state, then stops
    if code != 0:
        raise SystemExit(f"{name}, training seed {seed}: learning_curve.py failed with exit code {code}")


def summarize(recipes: dict[str, dict[str, Any]], out_dir: Path, seeds: list[int]) -> dict[str, Any]:
    """Per recipe: the final points' score and CPU minutes over the training seeds whose curve is finished."""
    summary: dict[str, Any] = {}
    for name, recipe in recipes.items():
        finals = {}
        for seed in seeds:
            last = [p for p in read_curve(curve_path(out_dir, name, seed)) if p["step"] == recipe["steps"]]
            if last:
                finals[seed] = last[0]
        if not finals:
            continue
        scores = np.array([p["score_mean"] for p in finals.values()])
        minutes = np.array([p["train_cpu_s"] / 60 for p in finals.values()])
        summary[name] = {
            "steps": recipe["steps"],
            "set": recipe.get("set") or {},
            "seeds": sorted(finals),
            "score_mean": float(scores.mean()),
            "score_stderr": standard_error(scores),
            "score_per_seed": {str(s): p["score_mean"] for s, p in finals.items()},
            "train_cpu_min_mean": float(minutes.mean()),
            "train_cpu_min_per_seed": {str(s): round(p["train_cpu_s"] / 60, 2) for s, p in finals.items()},
        }
    return summary


def draw(recipes: dict[str, dict[str, Any]], out_dir: Path, seeds: list[int], task: str) -> Path:
    """Score against training CPU minutes, mean over the seeds that reached each step, one line per recipe."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name in recipes:
        by_step: dict[int, list[dict[str, Any]]] = {}
        for seed in seeds:
            for point in read_curve(curve_path(out_dir, name, seed)):
                by_step.setdefault(point["step"], []).append(point)
        if not by_step:
            continue
        steps = sorted(by_step)
        minutes = [np.mean([p["train_cpu_s"] for p in by_step[s]]) / 60 for s in steps]
        score = [np.mean([p["score_mean"] for p in by_step[s]]) for s in steps]
        err = [standard_error(np.array([p["score_mean"] for p in by_step[s]])) for s in steps]
        ax.errorbar(minutes, score, yerr=err, marker="o", ms=3, capsize=2, label=name)
    ax.set_xlabel("training CPU minutes (all threads)")
    ax.set_ylabel("normalized score (validation episodes)")
    ax.set_title(f"{task}: phase-0 score against training CPU time\n(mean +- s.e. over training seeds {seeds})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    path = out_dir / "recipes.png"
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--task", required=True)
    parser.add_argument("--recipes", type=Path, required=True)
    parser.add_argument("--training-seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--every", type=int, default=500)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=7, help="episode seed (default 7: validation, not evaluation)")
    parser.add_argument("--out-dir", type=Path, default=Path("recipe-study"))
    parser.add_argument("--device", default="auto")
    parser.add_argument("--quiet", action="store_true", help="no progress bars while training")
    parser.add_argument("--only", nargs="+", metavar="RECIPE", help="train, summarize and draw only these recipes")
    parser.add_argument("--summary-only", action="store_true", help="summarize and draw what is there, train none")
    args = parser.parse_args()
    args.recipes_all = load_recipes(args.recipes)
    recipes = select_recipes(args.recipes_all, args.only, args.recipes)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    if not args.summary_only:
        for seed in args.training_seeds:  # every recipe on one seed before the next: comparable early
            for name, recipe in recipes.items():
                run_curve(args, name, recipe, seed)
    summary = summarize(recipes, args.out_dir, args.training_seeds)
    write_json(args.out_dir / "summary.json", {"task": args.task, "validation_seed": args.seed,
                                               "episodes": args.episodes, "recipes": summary})  # fmt: skip
    picture = draw(recipes, args.out_dir, args.training_seeds, args.task)
    for name, row in summary.items():
        print(f"{name:28s} {row['steps']:6d} steps  score {row['score_mean']:6.1f} +- {row['score_stderr']:4.1f} "
              f"over seeds {row['seeds']}  training {row['train_cpu_min_mean']:5.1f} CPU-min")  # fmt: skip
    print(f"wrote {args.out_dir / 'summary.json'} and {picture}")


if __name__ == "__main__":
    main()
