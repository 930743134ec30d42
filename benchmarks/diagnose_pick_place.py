"""Where KUKA pick-and-place is lost, stretch by stretch, on validation episodes (printed, never asserted): for each
stretch of ``horizon - 1`` steps, the block the guidance pulls (``pick_place.next_block``), whether the plan held it
(its flag on at some planned step), whether the cup really held it, and how far it ended from its target; and
for each block, in how many stretches a plan held it at all.

    python benchmarks/diagnose_pick_place.py WORKSPACE [--setups 1 2] [--alphas 10] [--seed 7] [--episodes 10]
        [--set KEY=VALUE ...] [--verbose]

WORKSPACE is a pipeline folder holding a trained KUKA model (after `dvc repro` of the quick-kuka profile); each
``--set`` is a dotted key of ``task.kuka-stacking`` (e.g. ``pick_place.next_block=free``); ``--verbose`` prints
every episode's stretches.
"""

from __future__ import annotations

import argparse

import numpy as np
from trained_workspace import add_workspace_args, load_trained, parse_settings

from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.families.kuka.execution import guided_blocks
from adaptdiffuser.families.kuka.scene import N_BLOCKS, N_JOINTS
from adaptdiffuser.families.kuka.tasks import PLACE_TARGETS, block_flags, block_positions, placed_count
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.planning import Planner

#: a block ending farther than this from the arm's base (xy, metres) was flung: the arm reaches about 1.2 m
REACH = 1.2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_workspace_args(parser, task="kuka-stacking", episodes=10)
    parser.add_argument("--setups", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--alphas", type=float, nargs="+", default=None, help="default: the workspace's alpha")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="dotted task keys")
    parser.add_argument("--verbose", action="store_true")
    args = parser.parse_args()
    ws = load_trained(args, episodes_section="pick_place")
    settings = parse_settings(args.set)
    task = ws.task_with(settings)
    family = get_family("kuka")
    planner = Planner(ws.bundle, make_sampler(task.planner.sampler, task.planner.sampler_steps), ws.device)
    p = task.settings.pick_place
    span = planner.horizon - 1
    if task.settings.planning.replan_every is not None:
        raise SystemExit("diagnose_pick_place: needs planning.replan_every null (one plan per stretch)")
    print(f"{ws.name} phase {args.phase} (training seed {args.training_seed}), {settings or 'as profiled'}: "
          f"{p.episodes} episodes per setup from seed {args.seed}")  # fmt: skip
    for alpha in args.alphas or [float(ws.raw["alpha"])]:
        for setup in args.setups:
            result, controller = family.pick_place_episodes(task, planner, alpha, setup, record=True)
            planned_held = cup_held = stretches = placed = 0
            by_block = np.zeros(N_BLOCKS, dtype=int)  # stretches whose plan held each block
            flung = int(
                sum((np.linalg.norm(block_positions(e[-1])[:, :2], axis=1) > REACH).sum() for e in result.executed)
            )
            moves = np.concatenate([np.abs(np.diff(e[:, :N_JOINTS], axis=0)).max(axis=1) for e in result.executed])
            for e, (executed, planned) in enumerate(zip(result.executed, controller.recorded, strict=True)):
                rows = []
                for k in range(p.replans):
                    real, plan = executed[k * span : (k + 1) * span + 1], planned[k * span : (k + 1) * span + 1]
                    b = guided_blocks(p.next_block, k, real[:1])[0]
                    by_block += (block_flags(plan) > 0.5).any(axis=0)
                    in_plan = bool((block_flags(plan)[:, b] > 0.5).any())
                    in_cup = bool((block_flags(real)[:, b] > 0.5).any())
                    away = np.linalg.norm(block_positions(real[-1])[b, :2] - PLACE_TARGETS[b, :2])
                    planned_held, cup_held, stretches = planned_held + in_plan, cup_held + in_cup, stretches + 1
                    rows.append(f"block {b}: plan {int(in_plan)} cup {int(in_cup)} {away:.2f} m")
                placed += placed_count(executed[-1])
                if args.verbose:
                    print(f"  episode {e}: placed {placed_count(executed[-1])}; " + " | ".join(rows))
            print(f"alpha {alpha:g}, setup {setup}: placed {placed}/{N_BLOCKS * len(result.executed)} blocks; "
                  f"the guided block held by the plan in {planned_held}/{stretches} stretches, by the cup in "
                  f"{cup_held}/{stretches}; stretches whose plan held block 0-3: {by_block.tolist()}; flung "
                  f"{flung}/{N_BLOCKS * len(result.executed)} blocks; joint move per step, 99th percentile "
                  f"{np.quantile(moves, 0.99):.3f} rad",
                  flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
