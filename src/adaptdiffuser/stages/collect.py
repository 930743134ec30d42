"""Stage ``collect``: expert data by D4RL's recipe, as Parquet."""

from __future__ import annotations

from pathlib import Path

import mlflow

from adaptdiffuser.config import Params
from adaptdiffuser.data.collect import collect
from adaptdiffuser.data.schema import write_trajectories
from adaptdiffuser.envs.factory import make_env
from adaptdiffuser.stages.common import EXPERT_DATA, file_digest
from adaptdiffuser.tracking import stage_run


def run_collect(params: Params, root: Path, progress: bool = True) -> Path:
    """Stage ``collect``: the expert dataset as Parquet."""
    with stage_run(
        params.task,
        "collect",
        0,
        {
            "env": params.section("env"),
            "expert": params.section("expert"),
            "collect": params.section("collect"),
        },
        root,
    ):
        env = make_env(params)
        traj = collect(params, env, progress=progress)
        out = root / EXPERT_DATA
        write_trajectories(out, traj)
        n_episodes = len(traj.episodes())
        mlflow.log_metrics({"steps": len(traj), "episodes": n_episodes, "goal_fraction": float(traj.reward.mean())})
        mlflow.log_param("data.sha256", file_digest(out))
    return out
