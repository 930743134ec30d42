"""Compare the Maze2D evolution recipes (``evolution.generate.recipe``: ``plans`` vs ``rollouts``) from the same
phase-0 model with the same seeds, in one command; prints a table (never asserts).

For each recipe, phases 1..K run as the pipeline runs them (generate, discriminate, select, fine-tune on expert
plus the selected data of phases 1..k, evaluate), through the family's library functions, in a scratch folder
(the workspace is only read). Each phase's model is evaluated on the task's evaluation episodes planning once and
replanning every ``--eval-replan`` steps, and its plans from states near the goal are measured: how far they wander
from the goal they are asked to end at (Diffuser's plans condition only the last state on the goal; data that reach
the goal and stay there should make them stay).

    python benchmarks/compare_maze_recipes.py WORKSPACE [--phases 2] [--tasks 256] [--set key=value ...]
    python benchmarks/compare_maze_recipes.py /tmp/ws --build --profile quick --set pretrain.steps=2000

WORKSPACE is a pipeline folder with ``params.yaml``, ``data/<task>/dataset.parquet`` and the phase-0 model
(``models/<task>/phase0/seed0`` or ``models/<task>/phase0``); with ``--build`` a missing dataset and phase-0 model
are made there first (collect and pretrain with the library, from ``--profile``'s params when the folder has no
params.yaml). ``--set`` overrides params keys (dotted, YAML values) for this comparison only.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from adaptdiffuser.checkpoint import ModelBundle, load_bundle, make_bundle, save_bundle
from adaptdiffuser.config import Params, TaskParams, apply_profile, params_from_dict, set_dotted
from adaptdiffuser.contract import TaskFiles
from adaptdiffuser.data.normalizer import fit_normalizer
from adaptdiffuser.data.schema import Trajectories, read_trajectories, write_trajectories
from adaptdiffuser.data.windows import MixedWindowDataset, WindowDataset, joint_array, subset_episodes
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.evaluation import normalized_score, run_episodes, standard_error
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.planning import Planner
from adaptdiffuser.seeding import derive_seed
from adaptdiffuser.training import train

CPU = torch.device("cpu")
PROFILES = Path(__file__).resolve().parents[1] / "profiles"


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--task", default=None, help="a maze2d task of params (default: the evolved task)")
    parser.add_argument("--recipes", nargs="+", default=["plans", "rollouts"])
    parser.add_argument("--phases", type=int, default=2, help="K: phases 1..K, each from the previous one")
    parser.add_argument("--tasks", type=int, default=None, help="generation tasks per phase (default: params)")
    parser.add_argument("--replan-every", type=int, default=None, help="rollouts' replanning (default: params)")
    parser.add_argument("--eval-replan", type=int, nargs="*", default=[32], help="evaluations beside plan-once")
    parser.add_argument("--episodes", type=int, default=None, help="evaluation episodes (default: params)")
    parser.add_argument("--near-goal-plans", type=int, default=64)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="params override")
    parser.add_argument("--build", action="store_true", help="collect and pretrain phase 0 where missing")
    parser.add_argument("--profile", default="quick", help="params for --build when WORKSPACE has none")
    parser.add_argument("--out", type=Path, default=None, help="scratch folder (default: a new temporary one)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--progress", action="store_true")
    return parser.parse_args()


# -- params -------------------------------------------------------------------------------------------------------


def load_raw(args: argparse.Namespace) -> dict[str, Any]:
    """The workspace's params (or the profile's, for --build) with the --set overrides."""
    path = args.workspace / "params.yaml"
    if not path.exists():
        if not args.build:
            raise SystemExit(f"{path}: not found (a pipeline workspace, or give --build)")
        args.workspace.mkdir(parents=True, exist_ok=True)
        apply_profile(args.profile, PROFILES, path)
    raw = yaml.safe_load(path.read_text())
    for item in args.set:
        key, _, value = item.partition("=")
        raw = set_dotted(raw, key, yaml.safe_load(value))
    return raw


def recipe_params(raw: dict[str, Any], task: str, recipe: str, args: argparse.Namespace) -> Params:
    """Params with ``recipe`` for ``task`` (and the command line's generation and evaluation sizes)."""
    raw = set_dotted(raw, "evolution.generate.recipe", recipe)
    if args.replan_every is not None:
        raw = set_dotted(raw, "evolution.generate.replan_every", args.replan_every)
    if args.tasks is not None:
        raw = set_dotted(raw, "evolution.generate.tasks", args.tasks)
    if args.episodes is not None:
        raw = set_dotted(raw, f"task.{task}.evaluate.episodes", args.episodes)
        raw = set_dotted(raw, f"task.{task}.evaluate.batch_size", args.episodes)
    declared = raw.get("phases") or {}
    raw["phases"] = {
        f"phase{k}": {**declared.get(f"phase{k}", {}), "previous": k - 1} for k in range(1, args.phases + 1)
    }
    return params_from_dict(raw)


# -- phase 0 ------------------------------------------------------------------------------------------------------


def phase0_dir(root: Path, task: str) -> Path:
    """The phase-0 model: per training seed (``phase0/seed0``) or, before seeds, ``phase0`` itself."""
    seeded = root / "models" / task / "phase0" / "seed0"
    return seeded if seeded.is_dir() else root / "models" / task / "phase0"


def expert_data(root: Path, task: TaskParams) -> Trajectories:
    """The expert episodes the models train on (the pretrain stage's subset)."""
    traj = read_trajectories(root / "data" / task.name / "dataset.parquet")
    return subset_episodes(traj, task.pretrain.expert_fraction, np.random.default_rng(task.pretrain.seed))


def build_phase0(root: Path, task: TaskParams, progress: bool) -> None:
    """Collect the dataset and pretrain the phase-0 model where they are missing (as collect and pretrain do)."""
    family = get_family(task.family)
    data = root / "data" / task.name / "dataset.parquet"
    if not data.exists():
        data.parent.mkdir(parents=True, exist_ok=True)
        write_trajectories(data, family.collect(task, TaskFiles(root, task.name), progress))
    out = phase0_dir(root, task.name)
    if (out / "ema.pt").exists():
        return
    traj = expert_data(root, task)
    torch.manual_seed(task.pretrain.seed)
    normalizer = fit_normalizer(family.normalizer_kind, joint_array(traj))
    meta = traj.metadata
    bundle = make_bundle(task.model, task.diffusion, meta["obs_dim"], meta["act_dim"], normalizer,
                         task=task.name, family=task.family, conditioning=family.conditioning, phase=0)  # fmt: skip
    train(bundle, WindowDataset(traj, task.diffusion.horizon, normalizer), task.pretrain, CPU, progress=progress)
    save_bundle(out, bundle)


def reference(root: Path, task: TaskParams, progress: bool) -> dict[str, Any]:
    """R_min and R_max of the task: the reference stage's file, or computed (it is cheap)."""
    path = root / "metrics" / "tasks" / task.name / "reference.json"
    if path.exists():
        return json.loads(path.read_text())
    return get_family(task.family).reference(task, TaskFiles(root, task.name), progress)


# -- one phase ----------------------------------------------------------------------------------------------------


def planner_of(bundle: ModelBundle, sampler: str, steps: int) -> Planner:
    return Planner(bundle, make_sampler(sampler, steps), CPU)


def evaluate(task: TaskParams, bundle: ModelBundle, replan_every: int, ref: dict[str, Any]) -> tuple[float, float]:
    """Score mean and standard error on the task's evaluation episodes, replanning every ``replan_every`` steps."""
    task = dataclasses.replace(task, planner=dataclasses.replace(task.planner, replan_every=replan_every))
    family = get_family(task.family)
    planner = planner_of(bundle, task.planner.sampler, task.planner.sampler_steps)
    controller = family.controller(task, planner, TaskFiles(Path("."), task.name), CPU)
    ev = task.evaluate
    result = run_episodes(lambda: family.make_simulator(task), controller, ev.episodes, ev.seed, ev.batch_size,
                          progress=False)  # fmt: skip
    scores = normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"])
    return float(np.mean(scores)), standard_error(scores)


def near_goal_plans(task: TaskParams, bundle: ModelBundle, n: int, seed: int = 0) -> dict[str, float]:
    """Plans from ``n`` random states in the goal's cell (within 0.3 of the goal, small velocity) to the goal:
    ``wander``, the mean over plans of the farthest they go from the goal (a plan that stays at the goal scores
    below the goal radius), and ``start_jump``, the median distance between a plan's first two states (the
    inpainted start and the first waypoint the follower heads for; physically at most about 0.05)."""
    env = get_family(task.family).make_simulator(task)
    rng = np.random.default_rng(seed)
    goal = env.goal_state()
    starts = np.concatenate([goal[:2] + rng.uniform(-0.3, 0.3, (n, 2)), rng.normal(0.0, 0.1, (n, 2))], axis=1)
    planner = planner_of(bundle, task.planner.sampler, task.planner.sampler_steps)
    plans = planner.plan(starts, np.tile(goal, (n, 1)), [derive_seed(seed, i) for i in range(n)])
    xy = plans[:, :, planner.act_dim : planner.act_dim + 2]
    return {
        "wander": float(np.linalg.norm(xy - goal[None, None, :2], axis=2).max(axis=1).mean()),
        "start_jump": float(np.median(np.linalg.norm(xy[:, 1] - xy[:, 0], axis=1))),
    }


def run_phase(
    params: Params, task: TaskParams, k: int, bundle: ModelBundle, expert: Trajectories, selected: list[Trajectories],
    out: Path, progress: bool,
) -> dict[str, Any]:  # fmt: skip
    """Phase k from ``bundle`` (trained in place): generate, discriminate, select, fine-tune; its figures."""
    family = get_family(task.family)
    cfg = params.phase(k)
    g, d, f = cfg.generate, cfg.discriminate, cfg.finetune
    files = TaskFiles(out, task.name)
    t0 = time.time()
    generated, stats = family.generate(task, planner_of(bundle, g.sampler, g.sampler_steps), files, g, params.alpha,
                                       derive_seed(g.seed, k), {"phase": k}, progress)  # fmt: skip
    judgement = family.discriminate(task, generated, d, k, files, progress)
    report = judgement.report()
    row = {"generated": report["generated"], "kept": report["kept"], "coin_kept": report["coin_kept"], **stats}
    row["reach"] = float(np.mean([t.steps_to_goal >= 0 for t in judgement.trajectories]))
    arrivals = [judgement.trajectories[i].steps_to_goal for i in judgement.kept]
    row["kept_arrival_mean"] = float(np.mean([a for a in arrivals if a >= 0])) if any(a >= 0 for a in arrivals) else -1
    row["generate_discriminate_s"] = time.time() - t0
    if not len(judgement.kept):
        row["stopped"] = "nothing kept"
        return row
    selected.append(family.selected_data(task, generated, judgement, {"phase": k}))
    write_trajectories(out / f"phase{k}" / "selected.parquet", selected[-1])
    h, norm = task.diffusion.horizon, bundle.normalizer
    parts = [WindowDataset(expert, h, norm)] + [WindowDataset(s, h, norm) for s in selected]
    share = (1.0 - f.expert_weight) / len(selected)
    row["synthetic_windows"] = len(parts[-1])
    steps = max(1, round(f.steps_fraction * task.pretrain.steps))
    train_cfg = dataclasses.replace(task.pretrain, steps=steps, seed=derive_seed(f.seed, k), ema_start=0)
    t0 = time.time()
    train(bundle, MixedWindowDataset(parts, [f.expert_weight] + [share] * len(selected)), train_cfg, CPU,
          progress=progress)  # fmt: skip
    row["finetune_s"] = time.time() - t0
    save_bundle(out / f"phase{k}" / "model", bundle)
    return row


def measure(task: TaskParams, bundle: ModelBundle, ref: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    row = near_goal_plans(task, bundle, args.near_goal_plans)
    for r in [0, *args.eval_replan]:
        row[f"score_r{r}"] = evaluate(task, bundle, r, ref)
    return row


# -- the comparison -----------------------------------------------------------------------------------------------


def fmt_score(value: tuple[float, float] | None) -> str:
    return "-" if value is None else f"{value[0]:6.1f} ± {value[1]:4.1f}"


def print_table(rows: list[dict[str, Any]], eval_replan: list[int]) -> None:
    head = ["phase", "recipe", "kept/gen", "reach", "L kept", "windows", "wander", "jump"]
    head += ["plan once"] + [f"replan {r}" for r in eval_replan]
    lines = [head]
    for r in rows:
        reach = r.get("reach")
        lines.append([
            str(r["phase"]), r["recipe"],
            f"{r['kept']}/{r['generated']}" if "kept" in r else "-",
            "-" if reach is None else f"{reach:.2f}",
            f"{r['kept_arrival_mean']:.0f}" if r.get("kept_arrival_mean", -1) >= 0 else "-",
            str(r.get("synthetic_windows", "-")),
            f"{r['wander']:.2f}" if "wander" in r else "-",
            f"{r['start_jump']:.2f}" if "start_jump" in r else "-",
            fmt_score(r.get("score_r0")),
            *[fmt_score(r.get(f"score_r{e}")) for e in eval_replan],
        ])  # fmt: skip
    widths = [max(len(line[i]) for line in lines) for i in range(len(head))]
    for line in lines:
        print("  ".join(cell.rjust(w) for cell, w in zip(line, widths, strict=True)))


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    raw = load_raw(args)
    base = params_from_dict(raw)
    task_name = args.task or base.evolve or base.tasks[0]
    out = args.out or Path(tempfile.mkdtemp(prefix="compare-maze-recipes-"))
    if args.build:
        build_phase0(args.workspace, base.resolve(task_name), args.progress)
    source = phase0_dir(args.workspace, task_name)
    ref = reference(args.workspace, base.resolve(task_name), args.progress)
    t_start = time.time()
    phase0 = load_bundle(source, CPU)
    task0 = recipe_params(raw, task_name, args.recipes[0], args).resolve(task_name)
    rows = [{"phase": 0, "recipe": "(both)", **measure(task0, phase0, ref, args)}]
    print(f"phase 0 ({source}): {rows[0]}", flush=True)
    for recipe in args.recipes:
        params = recipe_params(raw, task_name, recipe, args)
        task = params.resolve(task_name)
        expert = expert_data(args.workspace, task)
        bundle, selected = copy.deepcopy(phase0), []
        for k in range(1, args.phases + 1):
            row = {"phase": k, "recipe": recipe}
            row |= run_phase(params, task, k, bundle, expert, selected, out / recipe, args.progress)
            if "stopped" not in row:
                row |= measure(task, bundle, ref, args)
            rows.append(row)
            print(f"{recipe} phase {k}: {row}", flush=True)
            if "stopped" in row:
                break
    print(f"\n{task_name}: phases 1..{args.phases} from {source}, scratch {out}, {time.time() - t_start:.0f} s")
    print("kept/gen: navigation + coin trajectories kept of those generated; reach: share of executed plans (within")
    print("the horizon) or rollouts (within the episode) that reach the goal; L kept: mean steps to the goal of those")
    print("kept; windows: training windows of the phase's selected data; wander: mean farthest distance from the goal")
    print("of plans made near it; jump: their median first step; scores: normalized score, mean ± standard error")
    print("over the evaluation episodes, planning once or replanning\n")
    print_table(rows, args.eval_replan)


if __name__ == "__main__":
    main()
