"""The locomotion Diffuser baseline through the real stages on Walker2d and HalfCheetah (hopper-medium runs in the
DVC smoke pipeline): behaviour policy and dataset, reference, pretraining with the value function, and value-guided
evaluation under D4RL's score, with the smoke profile's tiny settings."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
import yaml
from smoke_project import narrow

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import Params, apply_profile, params_from_dict
from adaptdiffuser.data.schema import read_trajectories
from adaptdiffuser.families.locomotion.evolution import selection_rule
from adaptdiffuser.families.locomotion.family import episode_returns
from adaptdiffuser.families.locomotion.reference import normalized_score
from adaptdiffuser.family_registry import get_family
from adaptdiffuser.layout import (
    dataset_path,
    generated_path,
    model_dir,
    phase_metrics_path,
    reference_path,
    results_dir,
    resume_path,
    selected_path,
    value_dir,
    value_resume_path,
)
from adaptdiffuser.stages.collect import run_collect
from adaptdiffuser.stages.discriminate import run_discriminate
from adaptdiffuser.stages.evaluate import run_evaluate
from adaptdiffuser.stages.finetune import run_finetune
from adaptdiffuser.stages.generate import run_generate
from adaptdiffuser.stages.pretrain import pretrain_seed, run_pretrain
from adaptdiffuser.stages.reference import run_reference
from adaptdiffuser.stages.summarize import run_summarize
from adaptdiffuser.value_training import load_value

PROFILES = Path(__file__).resolve().parents[1] / "profiles"


def smoke_params(name: str, tmp_path: Path) -> Params:
    """The smoke profile's entry for ``name``, run as the only task (the DVC smoke pipeline does not list it)."""
    raw = yaml.safe_load(apply_profile("smoke", PROFILES, tmp_path / "params.yaml").read_text())
    return params_from_dict(narrow(raw, [name], unseen_tasks=[], evolve=None, phases={}))


@pytest.fixture(autouse=True)
def _tracking(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")


@pytest.mark.parametrize(
    ("name", "state_dim", "terminates"),
    [("walker2d-medium-replay", 18, True), ("halfcheetah-medium-expert", 18, False)],
)
def test_locomotion_baseline_stages(tmp_path: Path, name: str, state_dim: int, terminates: bool) -> None:
    params = smoke_params(name, tmp_path)
    settings = params.resolve(name).settings
    behaviour, steps = settings.behaviour, settings.episode_steps
    device = torch.device("cpu")
    run_collect(params, name, tmp_path, progress=False)
    traj = read_trajectories(tmp_path / dataset_path(name))
    assert traj.metadata["state_dim"] == state_dim and traj.sim_state.shape == (len(traj), state_dim)
    collect = tmp_path / "models" / name / "collect"
    assert (collect / "medium.zip").exists()
    assert json.loads((collect / "collect.json").read_text())["steps"] == len(traj)
    if name.endswith("medium-replay"):  # every transition the learner saw, up to the medium point (here: its budget)
        assert len(traj) >= behaviour.max_train_steps
    else:  # medium rollouts, then as many of the policy trained on to the expert budget
        assert len(traj) == 2 * behaviour.dataset_steps and (collect / "expert.zip").exists()

    ref = run_reference(params, name, tmp_path, progress=False)
    data = episode_returns(traj)
    assert ref["dataset"]["n_episodes"] == len(data)
    assert ref["dataset"]["score_mean"] == pytest.approx(float(np.mean(normalized_score(data, name))))
    assert json.loads((tmp_path / reference_path(name)).read_text())["r_max"] > ref["r_min"]

    run_pretrain(params, name, tmp_path, device, progress=False)
    bundle = load_bundle(tmp_path / model_dir(name, 0, 0))
    assert bundle.config["conditioning"] == "start" and bundle.normalizer.kind == "gaussian"
    assert (tmp_path / model_dir(name, 0, 0) / "value" / "value.pt").exists()

    metrics = run_evaluate(params, name, tmp_path, 0, device, progress=False)
    assert metrics["n_episodes"] == 2 and json.loads((tmp_path / phase_metrics_path(name, 0)).read_text()) == metrics
    assert metrics["seeds"]["0"]["score_mean"] == metrics["score_mean"]
    table = pq.read_table(tmp_path / results_dir(name, 0, 0) / "episodes.parquet").to_pydict()
    assert all(1 <= length <= steps for length in table["length"])
    if not terminates:  # HalfCheetah never falls: every episode runs its full length
        assert table["length"] == [steps, steps] and metrics["terminated_rate"] == 0.0
    assert table["score"] == pytest.approx(list(normalized_score(np.array(table["return"]), name)))
    summary = run_summarize(params, tmp_path)[name]
    assert summary["dataset"] == ref["dataset"] and summary["phase_0"]["score_mean"] == metrics["score_mean"]


def test_locomotion_evolution_phase(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """hopper-medium phase 1: value-guided segments from dataset states and resets, executed in the simulator from
    the same full state, selected by real reward; fine-tuned model and its equal-compute control; and phase 2's
    paper rule on reward per step x 1000. Before it, a pretraining stage rerun after its seed was trained (as DVC
    reruns a stage killed on a later seed, its outputs deleted) trains neither the model nor the value again."""
    name = "hopper-medium"
    raw = yaml.safe_load(apply_profile("smoke", PROFILES, tmp_path / "params.yaml").read_text())
    params = params_from_dict(narrow(raw, [name], unseen_tasks=[], evolve=name))
    device = torch.device("cpu")
    run_collect(params, name, tmp_path, progress=False)
    pretrain_seed(params, name, tmp_path, device, 0, progress=False)
    first_value = load_value(tmp_path / value_dir(name, 0))[0].state_dict()
    shutil.rmtree(tmp_path / model_dir(name, 0, 0))
    capsys.readouterr()
    run_pretrain(params, name, tmp_path, device, progress=False)
    printed = capsys.readouterr().out
    task = params.resolve(name)
    assert f"from step {task.pretrain.steps} ({tmp_path / resume_path(name, 0, 0)})" in printed
    assert f"from step {task.settings.value.steps} ({tmp_path / value_resume_path(name, 0)})" in printed
    for key, weights in load_value(tmp_path / value_dir(name, 0))[0].state_dict().items():
        torch.testing.assert_close(weights, first_value[key], rtol=0, atol=0)
    assert not list((tmp_path / "models" / ".resume").iterdir())  # the stage removed its states once all saved
    stats = run_generate(params, name, tmp_path, 1, device, progress=False)[0]
    g = params.phase(1).generate
    assert stats["generated"] == g.tasks and stats["from_dataset"] == g.tasks // 2
    generated = read_trajectories(tmp_path / generated_path(name, 1, 0))
    horizon = params.resolve(name).diffusion.horizon
    assert len(generated) == g.tasks * horizon and generated.extra["task_start_state"].shape == (len(generated), 12)

    report = run_discriminate(params, name, tmp_path, 1, progress=False)
    assert report["generated"] == g.tasks and report["kept"] >= 1
    selected = read_trajectories(tmp_path / selected_path(name, 1, 0))
    assert selected.sim_state is not None and not selected.terminal.any()
    # the kept rows are what the simulator did: replaying each segment's actions from its first state reproduces them
    sim = get_family("locomotion").make_simulator(params.resolve(name))
    first = selected.episodes()[0]
    sim.set_state(selected.sim_state[first.start])
    for row in range(first.start, first.stop - 1):
        step = sim.step(selected.action[row].astype(np.float64))
        np.testing.assert_allclose(step.observation, selected.observation[row + 1], atol=1e-5)
        assert step.reward == pytest.approx(float(selected.reward[row]), abs=1e-4)

    run_finetune(params, name, tmp_path, 1, device, progress=False)
    run_finetune(params, name, tmp_path, 1, device, progress=False, control=True)
    for control in (False, True):  # the value function travels with every model
        assert (tmp_path / model_dir(name, 1, 0, control) / "value" / "value.pt").exists()
    run_reference(params, name, tmp_path, progress=False)
    run_evaluate(params, name, tmp_path, 1, device, progress=False)
    gain = run_evaluate(params, name, tmp_path, 1, device, progress=False, control=True)
    assert gain["gain_n_episodes"] == params.resolve(name).evaluate.episodes

    rule = selection_rule(name, dataclasses.replace(params.phase(2).discriminate, rule="paper"), 2)
    assert rule.threshold == 3225  # the paper's phase-2 threshold for Hopper-medium
    kept = rule.select(np.array([3.3, 3.0, 10.0]), np.array([1, 1, 4]))  # 3300, 3000 and 2500 per 1000 steps
    assert kept.tolist() == [0]
