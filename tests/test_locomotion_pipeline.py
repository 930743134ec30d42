"""The locomotion Diffuser baseline through the real stages on Walker2d and HalfCheetah (hopper-medium runs in the
DVC smoke pipeline): behaviour policy and dataset, reference, pretraining with the value function, and value-guided
evaluation under D4RL's score, with tiny settings."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import params_from_dict
from adaptdiffuser.data.schema import read_trajectories
from adaptdiffuser.families.locomotion.family import episode_returns
from adaptdiffuser.families.locomotion.reference import normalized_score
from adaptdiffuser.stages.collect import run_collect
from adaptdiffuser.stages.common import dataset_path, model_dir, phase_metrics_path, reference_path, results_dir
from adaptdiffuser.stages.evaluate import run_evaluate
from adaptdiffuser.stages.pretrain import run_pretrain
from adaptdiffuser.stages.reference import run_reference
from adaptdiffuser.stages.summarize import run_summarize

TINY_BEHAVIOUR = {"max_train_steps": 1024, "max_expert_steps": 1536, "ppo_n_steps": 256, "batch_size": 64,
                  "eval_every": 512, "eval_episodes": 1, "dataset_steps": 600, "episode_steps": 200,
                  "torch_threads": 1}  # fmt: skip


def tiny_params(name: str, horizon: int):
    entry = {
        "family": "locomotion",
        "episode_steps": 30,
        "behaviour": TINY_BEHAVIOUR,
        "value": {"steps": 10, "batch_size": 4, "log_every": 5},
        "value_model": {"dim": 8, "dim_mults": [1, 2]},
        "guide": {"n_samples": 2},
        "model": {"dim": 8, "dim_mults": [1, 2]},
        "diffusion": {"horizon": horizon, "n_steps": 6, "clip_denoised": False, "action_weight": 10.0},
        "pretrain": {"steps": 10, "batch_size": 4, "ema_start": 5, "log_every": 5, "checkpoint_every": 5},
        "planner": {"sampler": "ddpm", "sampler_steps": 6},
        "evaluate": {"episodes": 2, "batch_size": 2, "pictures": 1, "seed": 7},
    }
    return params_from_dict({"tasks": [name], "coin_tasks": [], "evolve": None, "phases": {}, "task": {name: entry}})


@pytest.fixture(autouse=True)
def _tracking(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")


@pytest.mark.parametrize(
    ("name", "horizon", "state_dim", "terminates"),
    [("walker2d-medium-replay", 8, 18, True), ("halfcheetah-medium-expert", 4, 18, False)],
)
def test_locomotion_baseline_stages(tmp_path: Path, name: str, horizon: int, state_dim: int, terminates: bool) -> None:
    params = tiny_params(name, horizon)
    device = torch.device("cpu")
    run_collect(params, name, tmp_path, progress=False)
    traj = read_trajectories(tmp_path / dataset_path(name))
    assert traj.metadata["state_dim"] == state_dim and traj.sim_state.shape == (len(traj), state_dim)
    collect = tmp_path / "models" / name / "collect"
    assert (collect / "medium.zip").exists()
    assert json.loads((collect / "collect.json").read_text())["steps"] == len(traj)
    if name.endswith("medium-replay"):  # every transition the learner saw, up to the medium point (here: its budget)
        assert len(traj) >= TINY_BEHAVIOUR["max_train_steps"]
    else:  # medium rollouts, then as many of the policy trained on to the expert budget
        assert len(traj) == 2 * TINY_BEHAVIOUR["dataset_steps"] and (collect / "expert.zip").exists()

    ref = run_reference(params, name, tmp_path, progress=False)
    data = episode_returns(traj)
    assert ref["dataset"]["n_episodes"] == len(data)
    assert ref["dataset"]["score_mean"] == pytest.approx(float(np.mean(normalized_score(data, name))))
    assert json.loads((tmp_path / reference_path(name)).read_text())["r_max"] > ref["r_min"]

    run_pretrain(params, name, tmp_path, device, progress=False)
    bundle = load_bundle(tmp_path / model_dir(name, 0))
    assert bundle.config["conditioning"] == "start" and bundle.normalizer.kind == "gaussian"
    assert (tmp_path / model_dir(name, 0) / "value" / "value.pt").exists()

    metrics = run_evaluate(params, name, tmp_path, 0, device, progress=False)
    assert metrics["n_episodes"] == 2 and json.loads((tmp_path / phase_metrics_path(name, 0)).read_text()) == metrics
    table = pq.read_table(tmp_path / results_dir(name, 0) / "episodes.parquet").to_pydict()
    assert all(1 <= length <= 30 for length in table["length"])
    if not terminates:  # HalfCheetah never falls: every episode runs its full length
        assert table["length"] == [30, 30] and metrics["terminated_rate"] == 0.0
    assert table["score"] == pytest.approx(list(normalized_score(np.array(table["return"]), name)))
    summary = run_summarize(params, tmp_path)[name]
    assert summary["dataset"] == ref["dataset"] and summary["phase_0"]["score_mean"] == metrics["score_mean"]
