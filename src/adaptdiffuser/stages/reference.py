"""Stage ``reference``: the random and expert returns that anchor the normalized score."""

from __future__ import annotations

from pathlib import Path

import mlflow
import numpy as np

from adaptdiffuser.config import Params
from adaptdiffuser.envs.factory import make_env
from adaptdiffuser.evaluation import ExpertController, RandomController, run_episodes, standard_error
from adaptdiffuser.io import write_json
from adaptdiffuser.stages.common import REFERENCE
from adaptdiffuser.tracking import stage_run

# D4RL's reference returns (raw grid coordinates, their expert), for comparison only.
D4RL_REFERENCE = {"umaze": (23.85, 161.86), "medium": (13.13, 277.39), "large": (6.7, 273.99)}


def run_reference(params: Params, root: Path, progress: bool = True) -> dict:
    """Stage ``reference``: R_min (uniform random policy) and R_max (the expert) under the protocol."""
    ev = params.evaluate
    with stage_run(
        params.task,
        "reference",
        0,
        {
            "env": params.section("env"),
            "expert": params.section("expert"),
            "evaluate": params.section("evaluate"),
        },
        root,
    ):

        def factory():
            return make_env(params)

        random = run_episodes(
            factory,
            RandomController(ev.seed),
            ev.episodes,
            ev.seed,
            ev.batch_size,
            desc="reference: random",
            progress=progress,
        )
        expert = run_episodes(
            factory,
            ExpertController(ev.seed),
            ev.episodes,
            ev.seed,
            ev.batch_size,
            desc="reference: expert",
            progress=progress,
        )
        ref = {
            "r_min": float(np.mean(random.returns)),
            "r_max": float(np.mean(expert.returns)),
            "r_min_stderr": standard_error(random.returns),
            "r_max_stderr": standard_error(expert.returns),
            "n_episodes": ev.episodes,
            "expert_success_rate": float(np.mean(expert.final_success)),
        }
        if params.env.layout is None and params.env.maze in D4RL_REFERENCE:
            ref["d4rl_r_min"], ref["d4rl_r_max"] = D4RL_REFERENCE[params.env.maze]
        if ref["r_max"] <= ref["r_min"]:
            raise RuntimeError(f"expert return {ref['r_max']} does not exceed random return {ref['r_min']}")
        write_json(root / REFERENCE, ref)
        mlflow.log_metrics({k: v for k, v in ref.items() if isinstance(v, float)})
    return ref
