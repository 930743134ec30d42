"""Stage ``evaluate-coin``: a phase's planner on the unseen gold-coin task, guided toward the coin by ``alpha``."""

from __future__ import annotations

from pathlib import Path

import mlflow
import numpy as np
import torch

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import Params
from adaptdiffuser.diffusion.guidance import CoinObjective
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.evaluation import normalized_score, run_episodes
from adaptdiffuser.families.maze2d.execution import PlannerController
from adaptdiffuser.families.maze2d.gold_coin import coin_cases, coin_outcome, summarize_coin
from adaptdiffuser.families.registry import get_family
from adaptdiffuser.io import read_json, write_json
from adaptdiffuser.planning import Planner
from adaptdiffuser.plots import save_coin_picture
from adaptdiffuser.stages.common import (
    coin_metrics_path,
    coin_plots_dir,
    model_dir,
    reference_path,
    save_over_seeds,
)
from adaptdiffuser.tracking import stage_run


def run_evaluate_coin(
    params: Params, task_name: str, root: Path, phase: int, device: torch.device, progress: bool = True
) -> dict:
    """Stage ``evaluate-coin``: :func:`evaluate_coin_seed` for every training seed; write every seed's metrics and
    their mean to ``metrics/tasks/<task>/phase<k>-coin.json``."""
    task = params.resolve(task_name)
    if task.name not in params.coin_tasks:  # evaluate-coin@phase<k> follows `evolve`, whatever its family
        skipped = {"n_episodes": 0, "skipped": f"{task.name} is not in coin_tasks (no gold-coin variant)"}
        write_json(root / coin_metrics_path(task.name, phase), skipped)
        (root / coin_plots_dir(task.name, phase, 0)).parent.mkdir(parents=True, exist_ok=True)  # the stage's output
        return skipped
    ref = read_json(root / reference_path(task.name), f"reference scores of {task.name} (run reference@{task.name})")
    per_seed = {
        seed: {"gold_coin": evaluate_coin_seed(params, task.name, root, phase, device, seed, ref, progress)}
        for seed in params.seeds
    }
    metrics = save_over_seeds(per_seed, coin_metrics_path(task.name, phase), task.name, "evaluate-coin", phase, root)
    return metrics["gold_coin"]


def evaluate_coin_seed(
    params: Params,
    task_name: str,
    root: Path,
    phase: int,
    device: torch.device,
    seed: int,
    ref: dict,
    progress: bool = True,
) -> dict:
    """Plan each fixed coin case once with training seed ``seed``'s model of the phase, guided toward its coin with
    scale ``alpha``, follow the plan for a whole episode, and score pick / goal / both rates, plan collisions and
    the navigation score."""
    task = params.resolve(task_name)
    family = get_family(task.family)
    bundle = load_bundle(root / model_dir(task.name, phase, seed), device)
    gc, pl = task.settings.gold_coin, task.planner
    logged = {
        "gold_coin": task.section("gold_coin"),
        "alpha": params.alpha,
        "planner": task.section("planner"),
        "compile": {"sampling": params.compile.sampling},
        "seed": seed,
    }
    with stage_run(task.name, "evaluate-coin", phase, logged, root, seed=seed):
        env = family.make_simulator(task)
        cases = coin_cases(env, gc.cases_per_kind, np.random.default_rng(gc.seed))
        planner = Planner(bundle, make_sampler(pl.sampler, pl.sampler_steps), device, params.compile.sampling)
        coins = torch.as_tensor(cases.coins, dtype=torch.float32, device=device)

        def guidance_for(episodes: list[int]):
            return planner.guidance(CoinObjective(coins[episodes]), params.alpha)

        controller = PlannerController(planner, gc.seed, pl.replan_every, guidance_for=guidance_for)
        result = run_episodes(
            lambda: family.make_simulator(task),
            controller,
            len(cases),
            gc.seed,
            gc.batch_size,
            desc=f"gold coin phase {phase} seed {seed}",
            progress=progress,
            reset=lambda e, i: e.set_state(cases.starts[i]),
        )
        outcomes = [
            coin_outcome(env, executed, coin, gc.radius, plan)
            for executed, coin, plan in zip(result.executed, cases.coins, result.plans, strict=True)
        ]
        scores = normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"])
        gold = summarize_coin(outcomes, cases.kinds, scores)
        mlflow.log_metrics({f"gold_coin.{k}": float(v) for k, v in gold.items()})
        pictures = root / coin_plots_dir(task.name, phase, seed)
        goals = np.stack([env.goal_state()] * len(cases))
        picked = list(range(min(gc.pictures, len(cases))))
        if picked:
            # the unguided plans on the same noise as the guided first plans (each case's seed at t = 0)
            seeds = controller.seeds(picked, 0)
            plain = planner.plan(cases.starts[picked], goals[picked], seeds)[:, :, planner.act_dim :]
        for i in picked:
            picture = pictures / f"coin_{i:02d}.png"
            verdict = "picked + goal" if outcomes[i].both else ("picked" if outcomes[i].picked else "missed")
            save_coin_picture(
                env,
                picture,
                plain[i],
                result.plans[i],
                result.executed[i],
                cases.coins[i],
                gc.radius,
                f"phase {phase} seed {seed}, {cases.kinds[i]} coin, alpha {params.alpha:g}: {verdict}",
            )
            mlflow.log_artifact(str(picture), artifact_path="gold_coin")
    return gold
