"""KUKA stacking (and, with ``--pick-place``, pick-and-place) of one trained planner under several ways of planning
and executing, side by side on the same validation episodes (printed and written, never asserted): which of them
keeps the plans consistent with the real blocks.

Each variant sets dotted keys of the task (``task.kuka-stacking.<key>``); the default variants are the profile as it
is, resting blocks pinned to their real poses until the plan picks them up (``planning.pin_resting_blocks``),
replanning every 32 or 16 steps (``planning.replan_every``), both together, pinned with the full DDPM chain
(inpainting has every step to pull the arm to the blocks), and the reference's suction, which
takes a block at any distance (``control.suction_reach`` 10 m; the reference attaches whatever block the plan's
flag names, where it is, see docs/kuka.md), and the arm sent to the planned joints instead of following the real
blocks (``planning.follow_blocks`` false; quick-kuka follows them), with or without ``control.free_top_only``.
Per variant: the stacking score (mean +- standard error over episodes), the blocks the cup held at some step of an
episode (mean), the share of full towers, the CPU seconds, and the gain over the first variant paired per episode
(same seeds, same starts).

    python benchmarks/compare_kuka_planning.py WORKSPACE [--seed 7] [--episodes 20] [--phase 0] [--training-seed 0]
        [--variants FILE.yaml] [--pick-place | --pick-place-only] [--out FILE.json]

WORKSPACE is a pipeline folder holding a trained KUKA model (after `dvc repro` of the quick-kuka profile). A
variants file maps names to dotted settings, e.g. ``pinned: {planning.pin_resting_blocks: true}``; a variant's
``alpha`` is the guide scale of its pick-and-place episodes (the workspace's ``alpha`` otherwise).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from trained_workspace import add_workspace_args, load_trained

from adaptdiffuser.config import set_dotted
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.evaluation import normalized_score, paired_gain, run_episodes, standard_error
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.io import atomic_path
from adaptdiffuser.planning import Planner

VARIANTS: dict[str, dict[str, Any]] = {
    "as profiled": {},
    "pinned": {"planning.pin_resting_blocks": True},
    "replan every 32": {"planning.replan_every": 32},
    "replan every 16": {"planning.replan_every": 16},
    "pinned, replan every 32": {"planning.pin_resting_blocks": True, "planning.replan_every": 32},
    "pinned, DDPM (every diffusion step)": {"planning.pin_resting_blocks": True, "planner.sampler": "ddpm"},
    "suction at any distance": {"control.suction_reach": 10.0},
    "pinned, suction at any distance": {"planning.pin_resting_blocks": True, "control.suction_reach": 10.0},
    "the planned joints (not following the blocks)": {"planning.follow_blocks": False},
    "the planned joints, any top": {"planning.follow_blocks": False, "control.free_top_only": False},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_workspace_args(parser, task="kuka-stacking", episodes=20)
    parser.add_argument("--variants", type=Path, help="YAML: variant name -> {dotted task key: value}")
    parser.add_argument("--pick-place", action="store_true", help="also pick-and-place (validation seed, per setup)")
    parser.add_argument("--pick-place-only", action="store_true", help="pick-and-place alone (no stacking episodes)")
    parser.add_argument("--out", type=Path, help="write the figures here as JSON")
    args = parser.parse_args()
    variants = yaml.safe_load(args.variants.read_text()) if args.variants else VARIANTS
    ws = load_trained(args)
    args.pick_place = args.pick_place or args.pick_place_only
    if args.pick_place:  # the pick-and-place episodes on the same validation seed and count
        for key, value in (("seed", args.seed), ("episodes", args.episodes)):
            ws.raw = set_dotted(ws.raw, f"task.{ws.name}.pick_place.{key}", value)
    family = get_family("kuka")
    ref = ws.reference()
    print(
        f"{ws.name} phase {args.phase} (training seed {args.training_seed}): {args.episodes} episodes (per setup "
        f"in pick-and-place) from seed {args.seed}, torch threads {torch.get_num_threads()}",
        flush=True,
    )
    rows, first = [], None
    for name, settings in variants.items():
        settings = dict(settings)
        alpha = float(settings.pop("alpha", ws.raw["alpha"]))  # pick-and-place guide scale
        task = ws.task_with(settings)
        planner = Planner(ws.bundle, make_sampler(task.planner.sampler, task.planner.sampler_steps), ws.device)
        row: dict[str, Any] = {"variant": name, "settings": settings, "alpha": alpha}
        if not args.pick_place_only:
            cpu = time.process_time()
            result = run_episodes(
                lambda task=task: family.make_simulator(task),
                family.controller(task, planner, ws.files(), ws.device),
                task.evaluate.episodes,
                task.evaluate.seed,
                task.evaluate.batch_size,
                progress=False,
            )
            scores = normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"])
            row |= {"score_mean": float(scores.mean()), "score_stderr": standard_error(scores),
                    **family.episode_metrics(result), "cpu_s": round(time.process_time() - cpu, 1)}  # fmt: skip
            first = scores if first is None else first
            row["over_first"] = paired_gain(scores, first)
        if args.pick_place:
            cpu = time.process_time()
            unseen = family.evaluate_unseen(task, planner, alpha, ref, 0, name, False)
            row["pick_place"] = unseen | {"cpu_s": round(time.process_time() - cpu, 1)}
        rows.append(row)
        print(json.dumps(row), flush=True)
        if args.out is not None:
            with atomic_path(args.out) as tmp:
                tmp.write_text(json.dumps({"episodes": args.episodes, "seed": args.seed, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
