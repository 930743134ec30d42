"""Fine-tuning with a restarted Adam vs Adam carried on from phase 0, measured on a real Maze2D model (printed).

Builds the evolved Maze2D task of a profile as the pipeline does (expert data, phase-0 pretraining, phase-1
generate and discriminate), then fine-tunes phase 0 on expert + selected data twice, ``evolution.finetune.optimizer``
``restart`` and ``carry``, with the same seed: both runs see the same batches, diffusion times and noise, so the
per-step losses are paired. Prints, per mode: the loss of the first 1 / 10 / 100 steps (first, last, mean) and of
the whole run, the paired difference carry - restart, the loss phase 0's weights (not updated) get on the same
batches, how far the raw weights have moved after 1 / 10 / 100 steps, and (unless ``--no-eval``) the normalized
score of phase 0 and of both fine-tuned planners on the same evaluation episodes, with the paired gain.

    python benchmarks/bench_finetune_optimizer.py [--params profiles/quick.yaml] [--pretrain-steps N]
        [--collect-steps N] [--generate-tasks N] [--seeds 1 2] [--episodes N] [--no-eval] [--work DIR]

Phase 0 and the phase-1 data are cached under ``--work`` (keyed by their settings), so reruns only fine-tune.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from adaptdiffuser.checkpoint import ModelBundle, load_bundle, make_bundle, save_bundle
from adaptdiffuser.config import PretrainParams, TaskParams, load_params
from adaptdiffuser.contract import TaskFiles
from adaptdiffuser.data.normalizer import fit_normalizer
from adaptdiffuser.data.schema import Trajectories, read_trajectories, write_trajectories
from adaptdiffuser.data.windows import MixedWindowDataset, WindowDataset, joint_array
from adaptdiffuser.diffusion.conditions import training_conditions
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.evaluation import normalized_score, paired_gain, run_episodes, standard_error, summarize
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.planning import Planner
from adaptdiffuser.seeding import derive_seed
from adaptdiffuser.training import carried_optimizer, fingerprint, train

CPU = torch.device("cpu")
WINDOWS = (1, 10, 100)


def log(message: str) -> None:
    print(message, flush=True)


def cached_trajectories(path: Path, make: Callable[[], Trajectories | None]) -> Trajectories | None:
    """``make()``, written to ``path`` the first time and read back afterwards (None: nothing to keep)."""
    empty = path.with_suffix(".empty")
    if not path.exists() and not empty.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        traj = make()
        if traj is None:
            empty.touch()
        else:
            write_trajectories(path, traj)
    return read_trajectories(path) if path.exists() else None


def pretrain(task: TaskParams, traj: Trajectories, out: Path) -> tuple[ModelBundle, float]:
    """Phase 0 as the pretrain stage makes it (seeded init, the family's normalizer); cached in ``out``.
    Returns the bundle and the mean loss of its last 100 steps."""
    if not (out / "optimizer.pt").exists():
        family = get_family(task.family)
        torch.manual_seed(task.pretrain.seed)
        normalizer = fit_normalizer(family.normalizer_kind, joint_array(traj))
        meta = traj.metadata
        bundle = make_bundle(
            task.model, task.diffusion, meta["obs_dim"], meta["act_dim"], normalizer, conditioning=family.conditioning
        )
        start = time.perf_counter()
        history = train(
            bundle, WindowDataset(traj, task.diffusion.horizon, bundle.normalizer), task.pretrain, CPU, progress=False
        )
        bundle.config["bench_last_loss"] = history[-1][1]
        save_bundle(out, bundle)
        log(f"pretrained {task.pretrain.steps} steps in {time.perf_counter() - start:.0f} s")
    bundle = load_bundle(out)
    return bundle, float(bundle.config["bench_last_loss"])


def finetune_config(task: TaskParams, steps_fraction: float, seed: int) -> PretrainParams:
    """The fine-tune stage's training settings (pretrain's, ``steps_fraction`` of its steps, a seed derived from
    the phase, the EMA continued from the first step), logging every step."""
    steps = max(1, round(steps_fraction * task.pretrain.steps))
    return dataclasses.replace(task.pretrain, steps=steps, seed=derive_seed(seed, 1), ema_start=0, log_every=1)


def frozen_losses(bundle: ModelBundle, dataset: MixedWindowDataset, cfg: PretrainParams, n: int) -> list[float]:
    """The losses phase 0's raw weights get, without any update, on the first ``n`` batches ``train`` draws."""
    model = bundle.diffusion.train()
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator(device=CPU).manual_seed(cfg.seed)
    conditioning = bundle.config.get("conditioning", "start_goal")
    out = []
    with torch.no_grad():
        for _ in range(min(n, cfg.steps)):
            x0 = torch.from_numpy(dataset.sample(cfg.batch_size, rng))
            out.append(model.loss(x0, training_conditions(conditioning, x0, model.act_dim), generator=gen).item())
    model.eval()
    return out


def flat(bundle: ModelBundle) -> torch.Tensor:
    return torch.cat([p.detach().flatten().clone() for p in bundle.diffusion.model.parameters()])


def finetune(source: Path, dataset: MixedWindowDataset, cfg: PretrainParams, mode: str) -> dict[str, Any]:
    """Fine-tune phase 0 with Adam ``mode``; the per-step losses and how far the raw weights moved."""
    bundle = load_bundle(source)
    start_weights = flat(bundle)
    moved: dict[int, float] = {}

    def on_log(step: int, loss: float) -> None:
        if step in WINDOWS or step == cfg.steps:
            moved[step] = float((flat(bundle) - start_weights).norm() / start_weights.norm())

    began = time.perf_counter()
    history = train(
        bundle,
        dataset,
        cfg,
        CPU,
        on_log=on_log,
        progress=False,
        optimizer_state=carried_optimizer(bundle, mode, str(source)),
    )
    return {
        "bundle": bundle,
        "losses": [loss for _, loss in history],
        "moved": moved,
        "seconds": time.perf_counter() - began,
    }


def loss_lines(name: str, losses: list[float]) -> str:
    parts = []
    for n in WINDOWS:
        head = losses[:n]
        parts.append(
            f"first {n}: mean {np.mean(head):.4f}" + (f" (first {head[0]:.4f}, last {head[-1]:.4f})" if n > 1 else "")
        )
    parts.append(f"whole run ({len(losses)}): mean {np.mean(losses):.4f}, last 100 mean {np.mean(losses[-100:]):.4f}")
    return f"  {name:8s} " + "; ".join(parts)


def paired(a: list[float], b: list[float], n: int) -> str:
    d = np.asarray(a[:n]) - np.asarray(b[:n])
    return f"{d.mean():+.5f} +- {standard_error(d):.5f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="profiles/quick.yaml")
    parser.add_argument("--pretrain-steps", type=int, default=None, help="default: the profile's")
    parser.add_argument("--collect-steps", type=int, default=None, help="default: the profile's")
    parser.add_argument("--generate-tasks", type=int, default=None, help="default: the profile's phase 1")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="fine-tune seeds (default: phase 1's)")
    parser.add_argument("--episodes", type=int, default=None, help="evaluation episodes (default: the profile's)")
    parser.add_argument("--no-eval", action="store_true")
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_finetune_optimizer"))
    args = parser.parse_args()
    torch.set_num_threads(1)

    params = load_params(args.params)
    task = params.resolve(params.evolve or params.tasks[0])
    family = get_family(task.family)
    settings = task.settings
    if args.collect_steps:
        settings = dataclasses.replace(
            settings, collect=dataclasses.replace(settings.collect, steps=args.collect_steps)
        )
    pretrain_cfg = (
        task.pretrain if args.pretrain_steps is None else dataclasses.replace(task.pretrain, steps=args.pretrain_steps)
    )
    task = dataclasses.replace(task, settings=settings, pretrain=pretrain_cfg)
    phase = params.phase(1)
    g = (
        phase.generate
        if args.generate_tasks is None
        else dataclasses.replace(phase.generate, tasks=args.generate_tasks)
    )
    files = TaskFiles(args.work, task.name)

    data_key = fingerprint(dataclasses.asdict(settings))
    model_key = fingerprint(data_key, task.section("model"), task.section("diffusion"), task.section("pretrain"))
    gen_key = fingerprint(model_key, dataclasses.asdict(g), dataclasses.asdict(phase.discriminate), params.alpha)
    log(
        f"{args.params}: {task.name}, model {task.section('model')}, horizon {task.diffusion.horizon}, "
        f"pretrain {task.pretrain.steps} steps (batch {task.pretrain.batch_size}, lr {task.pretrain.lr}), "
        f"collect {settings.collect.steps} steps, generate {g.tasks} tasks; torch threads {torch.get_num_threads()}"
    )

    began = time.perf_counter()
    expert = cached_trajectories(
        args.work / f"expert-{data_key}.parquet", lambda: family.collect(task, files, progress=False)
    )
    source = args.work / f"phase0-{model_key}"
    phase0, pretrain_last = pretrain(task, expert, source)

    def make_selected() -> Trajectories | None:
        planner = Planner(phase0, make_sampler(g.sampler, g.sampler_steps), CPU)
        generated, stats = family.generate(task, planner, files, g, params.alpha, derive_seed(g.seed, 1), {}, False)
        judgement = family.discriminate(task, generated, phase.discriminate, 1, files, False)
        log(f"phase-1 data: {stats}, kept {len(judgement.kept)} plans")
        return family.selected_data(task, generated, judgement, {}) if len(judgement.kept) else None

    selected = cached_trajectories(args.work / f"selected-{gen_key}.parquet", make_selected)
    assert expert is not None
    h = task.diffusion.horizon
    parts, w = [WindowDataset(expert, h, phase0.normalizer)], phase.finetune.expert_weight
    if selected is None:
        log("no phase-1 plan was kept: fine-tuning on expert data only (the control's data)")
        w = 1.0
    else:
        parts.append(WindowDataset(selected, h, phase0.normalizer))
        log(f"phase-1 selected data: {len(selected)} steps, {len(parts[1])} windows")
    dataset = MixedWindowDataset(parts, [w, 1 - w][: len(parts)])
    adam_steps = phase0.optimizer["step"] if phase0.optimizer else 0
    log(
        f"data and phase 0 ready after {time.perf_counter() - began:.0f} s; phase 0's last pretraining steps "
        f"(expert data): mean loss {pretrain_last:.4f}; its Adam state: {adam_steps} steps"
    )

    runs: dict[tuple[int, str], dict[str, Any]] = {}
    for seed in args.seeds or [phase.finetune.seed]:
        cfg = finetune_config(task, phase.finetune.steps_fraction, seed)
        frozen = frozen_losses(load_bundle(source), dataset, cfg, 100)
        log(
            f"\nfine-tune seed {seed}: {cfg.steps} steps, lr {cfg.lr}, batch {cfg.batch_size}, "
            f"expert share {w}; per-step training losses (same batches and noise in both modes)"
        )
        for mode in ("restart", "carry"):
            runs[seed, mode] = run = finetune(source, dataset, cfg, mode)
            log(loss_lines(mode, run["losses"]) + f"  [{run['seconds']:.0f} s]")
        log(loss_lines("phase 0", frozen) + "  <- phase 0's weights, not updated (first 100 only)")
        r, c = runs[seed, "restart"]["losses"], runs[seed, "carry"]["losses"]
        log(
            "  carry - restart, paired per step: "
            + ", ".join(f"first {n}: {paired(c, r, n)}" for n in WINDOWS)
            + f", whole run: {paired(c, r, len(c))}"
        )
        log("  restart - phase 0, paired per step: " + ", ".join(f"first {n}: {paired(r, frozen, n)}" for n in WINDOWS))
        log("  carry - phase 0, paired per step:   " + ", ".join(f"first {n}: {paired(c, frozen, n)}" for n in WINDOWS))
        for mode in ("restart", "carry"):
            moved = runs[seed, mode]["moved"]
            log(f"  {mode:8s} raw weights moved |dw|/|w| after " + ", ".join(f"{s}: {v:.2e}" for s, v in moved.items()))

    if args.no_eval:
        return
    ev = task.evaluate if args.episodes is None else dataclasses.replace(task.evaluate, episodes=args.episodes)
    task = dataclasses.replace(task, evaluate=ev)
    ref = family.reference(task, files, progress=False)
    log(
        f"\nevaluation: {ev.episodes} episodes (seed {ev.seed}), EMA planners, {task.planner.sampler} "
        f"{task.planner.sampler_steps} steps; r_min {ref['r_min']:.1f}, r_max {ref['r_max']:.1f}"
    )

    def evaluate(bundle: ModelBundle) -> tuple[dict[str, float | int], np.ndarray]:
        planner = Planner(bundle, make_sampler(task.planner.sampler, task.planner.sampler_steps), CPU)
        result = run_episodes(
            lambda: family.make_simulator(task),
            family.controller(task, planner, files, CPU),
            ev.episodes,
            ev.seed,
            ev.batch_size,
            progress=False,
        )
        metrics = summarize(result, ref["r_min"], ref["r_max"]) | family.episode_metrics(result)
        scores = np.asarray(normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"]))
        return metrics, scores

    def line(name: str, m: dict[str, float | int]) -> str:
        extra = f", success {m['success_rate']:.2f}" if "success_rate" in m else ""
        return f"  {name:22s} score {m['score_mean']:.1f} +- {m['score_stderr']:.1f}{extra}"

    m0, _ = evaluate(load_bundle(source))
    log(line("phase 0", m0))
    for seed in args.seeds or [phase.finetune.seed]:
        (mr, sr), (mc, sc) = evaluate(runs[seed, "restart"]["bundle"]), evaluate(runs[seed, "carry"]["bundle"])
        gain = paired_gain(sc, sr)
        log(line(f"seed {seed} restart", mr))
        log(line(f"seed {seed} carry", mc))
        log(f"  seed {seed} carry - restart: {gain['gain_mean']:+.1f} +- {gain['gain_stderr']:.1f} (paired)")


if __name__ == "__main__":
    main()
