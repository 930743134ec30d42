"""Stage ``evaluate``: a phase's planner under the protocol; results, pictures and metrics."""

from __future__ import annotations

from pathlib import Path

import mlflow
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import Params
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.envs.factory import make_env
from adaptdiffuser.evaluation import normalized_score, run_episodes, summarize
from adaptdiffuser.io import atomic_path, read_json, write_json
from adaptdiffuser.planning import Planner, PlannerController
from adaptdiffuser.plots import save_plan_picture
from adaptdiffuser.stages.common import REFERENCE, model_dir, phase_metrics_path, plots_dir, results_dir
from adaptdiffuser.tracking import stage_run


def run_evaluate(params: Params, root: Path, phase: int, device: torch.device, progress: bool = True) -> dict:
    """Stage ``evaluate``: run the planner under the protocol; per-episode results, metrics and pictures."""
    ref = read_json(root / REFERENCE, "reference scores (run the reference stage)")
    bundle = load_bundle(root / model_dir(phase), device)
    ev, pl = params.evaluate, params.planner
    with stage_run(
        params.task,
        "evaluate",
        phase,
        {
            "env": params.section("env"),
            "planner": params.section("planner"),
            "evaluate": params.section("evaluate"),
            "model": {"path": str(model_dir(phase)), "data": bundle.config.get("data", {})},
        },
        root,
    ):
        planner = Planner(bundle, make_sampler(pl.sampler, pl.sampler_steps), device)
        controller = PlannerController(planner, ev.seed, pl.replan_every)
        result = run_episodes(
            lambda: make_env(params),
            controller,
            ev.episodes,
            ev.seed,
            ev.batch_size,
            desc=f"evaluate phase {phase}",
            progress=progress,
        )
        navigation = summarize(result, ref["r_min"], ref["r_max"])
        scores = normalized_score(np.asarray(result.returns), ref["r_min"], ref["r_max"])
        table = pa.table(
            {
                "episode": result.episodes,
                "start_x": [s[0] for s in result.starts],
                "start_y": [s[1] for s in result.starts],
                "goal_x": [g[0] for g in result.goals],
                "goal_y": [g[1] for g in result.goals],
                "return": result.returns,
                "score": scores,
                "final_success": result.final_success,
                "first_goal_step": result.first_goal_step,
            }
        )
        out = root / results_dir(phase) / "episodes.parquet"
        out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(out) as tmp:
            pq.write_table(table, tmp)
        env = make_env(params)
        pictures = root / plots_dir(phase)
        for i in range(min(ev.pictures, ev.episodes)):
            picture = pictures / f"plan_{i:02d}.png"
            save_plan_picture(
                env,
                picture,
                result.plans[i],
                result.executed[i],
                f"phase {phase}, episode {i}: return {result.returns[i]:.0f}, score {scores[i]:.0f}",
                goal=result.goals[i],
            )
            mlflow.log_artifact(str(picture), artifact_path="plans")
        write_json(root / phase_metrics_path(phase), {"navigation": navigation})
        mlflow.log_metrics({f"navigation.{k}": float(v) for k, v in navigation.items()})
        mlflow.log_artifact(str(out))
    return navigation
