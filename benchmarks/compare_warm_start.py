"""Score and evaluation time of a value-guided (locomotion) planner replanning from pure noise against replanning
warm-started from its last plan, and of its guide scale, side by side on the same episodes over training seeds
(printed and written, never asserted).

Every decision after an episode's first can start from the plan executed last, shifted by one step and noised to
diffusion step K (``guide.warm_start_step``), so its chain runs K + 1 denoising steps instead of all of them. For
each training seed of ``--training-seeds``, the task's phase-k model is evaluated under the task's protocol on
``--episodes`` episodes from ``--seed`` (a validation seed by default, not ``evaluate.seed``: choose on it, then
confirm once on the evaluation seed):

* replanning from pure noise, and warm-started at each K of ``--warm-steps``, all at the task's guide scale; the
  gain of each K over pure noise is paired per episode;
* each guide scale of ``--scales`` (0 = unguided: the first action of the best of N unguided plans by value),
  replanning as the task does (its own ``warm_start_step``), paired with the task's own scale;
* each guide scale of ``--noise-scales``, replanning from pure noise, paired with pure noise at the task's scale;
* each number of samples per decision of ``--samples`` (Diffuser: 64), replanning as the task does at its scale,
  paired with the task's own number.
  Guidance acts at the steps ``t >= t_stopgrad`` only, so a warm start at K = ``t_stopgrad`` guides one step of
  its chain: this is where a scale acts on the whole chain, as in Diffuser.

Over the training seeds: the mean of the per-seed scores and paired gains, +- their standard error over seeds.
Every evaluation is written to ``--out`` (JSON) as soon as it is measured; the same command continues a stopped
comparison.

    python benchmarks/compare_warm_start.py WORKSPACE [--task hopper-medium] [--warm-steps 2 4 8]
        [--scales 0 0.3] [--noise-scales 0 0.3] [--samples 64] [--seed 7] [--episodes 10] [--phase 0]
        [--training-seeds 0 1 2] [--out FILE]

WORKSPACE is a pipeline folder after `dvc repro` (its params.yaml, models/, value functions and reference.json).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from trained_workspace import add_workspace_args, load_trained

from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.evaluation import normalized_score, paired_gain, run_episodes, standard_error
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.io import atomic_path
from adaptdiffuser.planning import Planner

NOISE = "pure noise"


def variants(
    warm_steps: list[int],
    scales: list[float],
    own_scale: float,
    own_warm: int | None,
    noise_scales: Sequence[float] = (),
    samples: Sequence[int] = (),
    own_samples: int | None = None,
) -> dict[str, dict]:
    """``label -> {warm, scale, over}``: pure noise and each warm start at the task's scale (over pure noise), then
    each scale of ``scales`` replanning as the task does, over the task's own scale, and each of ``noise_scales``
    replanning from pure noise, over pure noise at the task's scale (a task that replans from pure noise itself
    has them among ``scales`` already), and each of ``samples`` (plans per decision) replanning as the task does, over
    the task's own ``own_samples``. A setting's ``samples`` None is the task's."""
    table: dict[str, dict] = {NOISE: {"warm": None, "scale": own_scale, "over": None}}
    own = NOISE
    if own_warm is not None:
        own = f"scale {own_scale:g}, warm {own_warm} (the task's)"
        table[own] = {"warm": own_warm, "scale": own_scale, "over": None}
    for warm in warm_steps:
        if warm != own_warm:
            table[f"warm start at step {warm}"] = {"warm": warm, "scale": own_scale, "over": NOISE}
    for scale in scales:
        if scale != own_scale:
            table[f"scale {scale:g}"] = {"warm": own_warm, "scale": scale, "over": own}
    for scale in noise_scales:
        if scale != own_scale and not (own_warm is None and scale in scales):
            table[f"pure noise, scale {scale:g}"] = {"warm": None, "scale": scale, "over": NOISE}
    for n in samples:
        if n != own_samples:
            table[f"{n} samples per decision"] = {"warm": own_warm, "scale": own_scale, "over": own, "samples": n}
    if own_warm is not None and own_warm in warm_steps:
        table[own]["over"] = NOISE  # the task's own warm start is one of those compared with pure noise
    return table


def evaluate(ws: Any, warm: int | None, scale: float, samples: int | None = None) -> dict[str, Any]:
    """One setting of the planner over the workspace's episodes: per-episode scores, lengths and time."""
    settings: dict[str, Any] = {"guide.warm_start_step": warm, "guide.scale": scale}
    if samples is not None:
        settings["guide.n_samples"] = samples
    task = ws.task_with(settings)
    family = get_family(task.family)
    ev = task.evaluate
    planner = Planner(ws.bundle, make_sampler(task.planner.sampler, task.planner.sampler_steps), ws.device)
    start = time.perf_counter()
    result = run_episodes(lambda: family.make_simulator(task), family.controller(task, planner, ws.files(), ws.device),
                          ev.episodes, ev.seed, ev.batch_size, progress=False)  # fmt: skip
    elapsed = time.perf_counter() - start
    ref = ws.reference()
    scores = normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"])
    batches = [result.lengths[i : i + ev.batch_size] for i in range(0, ev.episodes, ev.batch_size)]
    per_step_ms = 1000 * elapsed / sum(max(b) for b in batches)  # a batch decides until its longest episode ends
    return {"scores": [float(s) for s in scores], "length_mean": float(np.mean(result.lengths)),
            "eval_s": round(elapsed, 1), "ms_per_decision": round(per_step_ms, 1)}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_workspace_args(parser)
    parser.add_argument("--warm-steps", type=int, nargs="+", default=[2, 4, 8])
    parser.add_argument("--scales", type=float, nargs="*", default=[], help="guide scales to compare (0: unguided)")
    parser.add_argument(
        "--noise-scales",
        type=float,
        nargs="*",
        default=[],
        help="guide scales to compare replanning from pure noise (guided over the whole chain)",
    )
    parser.add_argument("--samples", type=int, nargs="*", default=[], help="plans per decision to compare")
    parser.add_argument("--training-seeds", type=int, nargs="+", default=None, help="default: --training-seed")
    parser.add_argument("--out", type=Path, default=None, help="default: compare_warm_start.json in WORKSPACE")
    args = parser.parse_args()
    seeds = args.training_seeds or [args.training_seed]
    out = args.out or args.workspace / "compare_warm_start.json"
    record: dict[str, Any] = json.loads(out.read_text()) if out.exists() else {}
    record.setdefault("runs", {})
    for seed in seeds:
        args.training_seed = seed
        ws = load_trained(args)
        base = ws.task()
        guide = base.settings.guide
        table = variants(args.warm_steps, args.scales, guide.scale, guide.warm_start_step, args.noise_scales,
                         args.samples, guide.n_samples)  # fmt: skip
        setup = {"task": ws.name, "phase": args.phase, "episode_seed": args.seed, "episodes": base.evaluate.episodes}
        if any(record.get(key, value) != value for key, value in setup.items()):
            parser.error(f"{out} holds another comparison ({ {k: record.get(k) for k in setup} }): give --out")
        record |= setup | {"torch_threads": torch.get_num_threads(), "variants": table}
        runs = record["runs"].setdefault(str(seed), {})
        for label, setting in table.items():
            if label not in runs:
                runs[label] = evaluate(ws, setting["warm"], setting["scale"], setting.get("samples")) | setting
                with atomic_path(out) as tmp:  # a kill mid-write leaves the last whole file
                    tmp.write_text(json.dumps(record, indent=1) + "\n")
            run = runs[label]
            score, stderr = np.mean(run["scores"]), standard_error(np.array(run["scores"]))
            print(f"seed {seed} {label:>34}: score {score:6.1f} +- {stderr:4.1f}, mean length "
                  f"{run['length_mean']:6.1f}, evaluation {run['eval_s']:6.1f} s ({run['ms_per_decision']:.0f} ms "
                  "per decision)", flush=True)  # fmt: skip
    summary: dict[str, Any] = {}
    print(f"over training seeds {seeds} (mean of per-seed values +- standard error over seeds):")
    for label, setting in table.items():
        runs_of = [record["runs"][str(s)] for s in seeds]
        scores = np.array([np.mean(runs[label]["scores"]) for runs in runs_of])
        row: dict[str, Any] = {"score_mean": float(scores.mean()), "score_stderr": standard_error(scores)}
        line = f"  {label:>34}: score {row['score_mean']:6.1f} +- {row['score_stderr']:4.1f}"
        if setting["over"] is not None:
            per_seed = [
                paired_gain(np.array(r[label]["scores"]), np.array(r[setting["over"]]["scores"])) for r in runs_of
            ]
            g = np.array([gain["gain_mean"] for gain in per_seed])
            row |= {"over": setting["over"], "gain_mean": float(g.mean()), "gain_stderr": standard_error(g),
                    "gain_per_seed": {str(s): gain for s, gain in zip(seeds, per_seed, strict=True)}}  # fmt: skip
            line += f", gain over {setting['over']}: {row['gain_mean']:+6.1f} +- {row['gain_stderr']:4.1f}"
        summary[label] = row
        print(line)
    record |= {"summary": summary, "training_seeds": seeds}
    with atomic_path(out) as tmp:
        tmp.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
