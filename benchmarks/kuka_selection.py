"""What KUKA's discriminator would keep from one trained planner's generated pick-and-place episodes (printed and
written, never asserted): the distribution of the episodes' tracking errors and blocks placed, and, for each
candidate ``max_error``, how many pass tracking, the range check too, and how many the paper's rule (more than 1.5
blocks placed) and the profile's rule keep; how many executed episodes, and how many plans, stay within the range
check. It chooses the threshold on generated episodes, never on evaluation episodes.

The episodes are phase ``--phase``'s generation for training seed ``--training-seed``, exactly as the
``generate@phase<k>`` stage draws them (its seed, tasks, sampler and ``alpha``) from the model of the phase before,
unless ``--tasks`` asks for fewer; they are judged as ``discriminate@phase<k>`` judges them, with every threshold.

    python benchmarks/kuka_selection.py WORKSPACE [--phase 1] [--training-seed 0] [--tasks N]
        [--thresholds 0.05,0.1,0.2,0.3,0.5,1.02] [--model DIR] [--set KEY=VALUE ...] [--out FILE.json]

WORKSPACE is a pipeline folder of a KUKA profile with its stacking data and the model the phase starts from
(`models/<task>/phase<k-1>/seed<s>`, or ``--model``, e.g. a ``learning_curve.py --keep-model`` folder); each
``--set`` is a dotted key of the task (e.g. ``control.max_joint_step=0.1``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
import yaml
from trained_workspace import parse_settings, with_task_settings

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import params_from_dict
from adaptdiffuser.data.schema import read_trajectories
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.evolution.discriminator import select
from adaptdiffuser.families.kuka.evolution import judge_episodes, selection_rule, within_range
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.io import atomic_path
from adaptdiffuser.layout import dataset_path, model_dir
from adaptdiffuser.planning import Planner
from adaptdiffuser.stages.common import resolve_device
from adaptdiffuser.stages.generate import generation_seed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--task", default=None, help="default: the evolved task")
    parser.add_argument("--phase", type=int, default=1)
    parser.add_argument("--training-seed", type=int, default=0)
    parser.add_argument("--tasks", type=int, default=None, help="default: the phase's evolution.generate.tasks")
    parser.add_argument("--thresholds", default="0.05,0.1,0.2,0.3,0.5,1.02", help="candidate max_error values")
    parser.add_argument("--model", type=Path, default=None, help="default: the model the phase starts from")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="dotted task keys")
    parser.add_argument("--out", type=Path, default=None, help="default: kuka_selection-phase<k>-seed<s>.json")
    parser.add_argument("--device", default="auto")
    args = parser.parse_args()
    root = args.workspace.resolve()
    raw = yaml.safe_load((root / "params.yaml").read_text())
    name = args.task or raw.get("evolve")
    if name is None:
        parser.error("the workspace's params evolve no task: name one with --task")
    settings = parse_settings(args.set)
    params = params_from_dict(with_task_settings(raw, name, settings))
    task, cfg = params.resolve(name), params.phase(args.phase)
    family = get_family(task.family)
    if task.family != "kuka":
        parser.error(f"{name} is a {task.family} task: this study is KUKA's")
    g = cfg.generate if args.tasks is None else dataclasses.replace(cfg.generate, tasks=args.tasks)
    device = resolve_device(args.device)
    model = args.model or root / model_dir(name, cfg.previous, args.training_seed)
    planner = Planner(load_bundle(model, device), make_sampler(g.sampler, g.sampler_steps), device)
    seed = generation_seed(g, args.phase, args.training_seed)
    judge_all = dataclasses.replace(cfg.discriminate, max_error=1e9)  # every episode tracks: thresholds come after
    generated, stats = family.generate(task, planner, None, g, params.alpha, seed, {}, progress=True)

    expert = read_trajectories(root / dataset_path(name), name).observation
    judgement = judge_episodes(family.make_simulator, task, generated, judge_all, expert, None, progress=True)
    tracked = judgement.trajectories
    errors = np.array([t.max_error for t in tracked])
    placed = np.array([t.total_reward for t in tracked])
    excess = task.settings.selection.max_range_excess
    low, high = expert.min(axis=0), expert.max(axis=0)
    in_range = np.array([within_range(t.observations, low, high, excess) for t in tracked])
    plans = [generated.observation[e] for e in generated.episodes()]
    planned_in_range = np.array([within_range(plan, low, high, excess) for plan in plans])
    paper = dataclasses.replace(cfg.discriminate, rule="paper")
    rows = []
    for threshold in (float(x) for x in args.thresholds.split(",")):
        tracks = errors <= threshold
        passed = np.flatnonzero(tracks & in_range)
        kept = select(tracked, passed, selection_rule(cfg.discriminate))
        rows.append(
            {
                "max_error": threshold,
                "pass_tracking": int(tracks.sum()),
                "pass_both": len(passed),
                "kept_profile_rule": len(kept),
                "placed_mean_kept": float(placed[kept].mean()) if len(kept) else 0.0,
                "kept_paper_rule": len(select(tracked, passed, selection_rule(paper))),
            }
        )
    result = {
        "workspace": str(root),
        "model": str(model),
        "phase": args.phase,
        "training_seed": args.training_seed,
        "generation_seed": seed,
        "settings": settings,
        "tasks": g.tasks,
        "follow_blocks": task.settings.planning.follow_blocks,
        "rule": cfg.discriminate.rule,
        "tracking_error_quantiles": {
            f"q{int(q * 100)}": float(np.quantile(errors, q)) for q in (0.1, 0.25, 0.5, 0.75, 0.9)
        },
        "placed_counts": {str(k): int((placed == k).sum()) for k in range(5)},
        "in_range": int(in_range.sum()),  # executed states within the range check
        "planned_in_range": int(planned_in_range.sum()),  # the plans themselves
        "placed_mean_while_generating": stats["placed_mean_while_generating"],
        "thresholds": rows,
    }
    print(json.dumps(result, indent=1))
    out = args.out or root / f"kuka_selection-phase{args.phase}-seed{args.training_seed}.json"
    with atomic_path(out) as tmp:
        tmp.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
