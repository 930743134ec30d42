"""The evolution stages in process on the smoke profile: generate, discriminate and fine-tune phase 1 from a real
phase 0 (real simulator, real Parquet, real MLflow in a temporary sqlite store)."""

from __future__ import annotations

import csv
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

import adaptdiffuser.stages.finetune as finetune_stage
from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.config import Params, apply_profile, load_params
from adaptdiffuser.data.schema import read_trajectories
from adaptdiffuser.diffusion.samplers import DDIMSampler
from adaptdiffuser.layout import (
    discriminator_metrics_path,
    discriminator_plot_path,
    generated_path,
    model_dir,
    phase_metrics_path,
    plots_dir,
    results_dir,
    seed_record_dir,
    selected_path,
    unseen_metrics_path,
    unseen_plots_dir,
)
from adaptdiffuser.planning import Planner
from adaptdiffuser.stages.collect import run_collect
from adaptdiffuser.stages.discriminate import run_discriminate
from adaptdiffuser.stages.evaluate import run_evaluate
from adaptdiffuser.stages.evaluate_unseen import run_evaluate_unseen
from adaptdiffuser.stages.finetune import finetune_config, run_finetune
from adaptdiffuser.stages.generate import run_generate
from adaptdiffuser.stages.pretrain import run_pretrain
from adaptdiffuser.stages.reference import run_reference
from adaptdiffuser.stages.report import run_report
from adaptdiffuser.stages.summarize import run_summarize

REPO = Path(__file__).resolve().parents[1]
CPU = torch.device("cpu")
TASK = "maze2d-umaze"  # the smoke profile's evolved task


def _with_phase1(params: Params, **discriminate: object) -> Params:
    phase = params.phase(1)
    changed = dataclasses.replace(phase, discriminate=dataclasses.replace(phase.discriminate, **discriminate))
    return dataclasses.replace(params, phases=(changed, *params.phases[1:]))


@pytest.fixture(scope="module")
def phase1_root(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Params]:
    """A project folder after collect, pretrain, generate@phase1, discriminate@phase1 and finetune@phase1."""
    root = tmp_path_factory.mktemp("evolution")
    apply_profile("smoke", REPO / "profiles", root / "params.yaml")
    params = load_params(root / "params.yaml")
    assert params.evolve == TASK
    run_collect(params, TASK, root, progress=False)
    run_pretrain(params, TASK, root, CPU, progress=False)
    run_generate(params, TASK, root, 1, CPU, progress=False)
    run_discriminate(params, TASK, root, 1, progress=False)
    run_finetune(params, TASK, root, 1, CPU, progress=False)
    return root, params


def test_generated_file_holds_one_plan_per_task(phase1_root: tuple[Path, Params]) -> None:
    root, params = phase1_root
    generated = read_trajectories(root / generated_path(TASK, 1, 0))
    assert generated_path(TASK, 1, 0) == Path(f"data/{TASK}/phase1/generated/seed0.parquet")
    assert generated.metadata["source"] == "synthetic" and generated.metadata["env"] == TASK
    assert len(generated.episodes()) == params.phase(1).generate.tasks
    assert len(generated) == params.phase(1).generate.tasks * params.resolve(TASK).diffusion.horizon
    # each plan starts at its task's start and ends at its goal (inpainting)
    first = generated.episodes()[3]
    np.testing.assert_allclose(generated.observation[first][0], generated.extra["task_start"][first][0], atol=1e-4)
    np.testing.assert_allclose(generated.observation[first][-1], generated.extra["task_goal"][first][0], atol=1e-4)


def test_selected_file_and_report(phase1_root: tuple[Path, Params]) -> None:
    root, params = phase1_root
    selected = read_trajectories(root / selected_path(TASK, 1, 0))
    report = json.loads((root / discriminator_metrics_path(TASK, 1)).read_text())
    assert report["n_seeds"] == 1 and report["seeds"]["0"]["kept"] == report["kept"]
    assert report["kept"] == len(selected.episodes()) >= 1
    assert report["generated"] == params.phase(1).generate.tasks
    assert report["kept"] + report["rejected_tracking"] + report["rejected_reward"] == report["generated"]
    assert (root / discriminator_plot_path(TASK, 1, 0)).read_bytes()[:4] == b"\x89PNG"


def test_finetuned_model_loads_keeps_the_normalizer_and_plans(phase1_root: tuple[Path, Params]) -> None:
    root, params = phase1_root
    task = params.resolve(TASK)
    assert model_dir(TASK, 1, 0) == Path(f"models/{TASK}/phase1/seed0")
    phase0 = load_bundle(root / model_dir(TASK, 0, 0))
    phase1 = load_bundle(root / model_dir(TASK, 1, 0))
    assert phase1.config["phase"] == 1 and phase1.config["previous"] == 0
    assert phase1.normalizer.state_dict() == phase0.normalizer.state_dict()
    assert set(phase1.config["data"]["synthetic"]) == {"phase1"}
    # phase 1 continues phase 0's weights: every tensor moved, none further than Adam's steps can take it
    # (|update| <= lr (1 - beta1) / sqrt(1 - beta2) ~ 3.2 lr per step), far less than a re-initialization would
    train_cfg = finetune_config(params, task, 1, 0)
    bound = 3.2 * train_cfg.lr * train_cfg.steps
    for (name, a), b in zip(phase0.diffusion.named_parameters(), phase1.diffusion.parameters(), strict=True):
        assert not torch.equal(a, b), f"{name} was not fine-tuned"
        assert (a - b).abs().max().item() <= bound, name
    planner = Planner(phase1, DDIMSampler(task.planner.sampler_steps), CPU)
    starts = np.array([[1.0, 1.0, 0.0, 0.0], [3.0, 1.0, 0.1, -0.1]])
    goals = np.array([[1.0, 3.0, 0.0, 0.0], [1.0, 3.0, 0.0, 0.0]])
    plan = planner.plan(starts, goals, [0, 1])
    assert plan.shape == (2, task.diffusion.horizon, 6) and np.isfinite(plan).all()
    np.testing.assert_allclose(plan[:, 0, 2:], starts, atol=1e-4)
    np.testing.assert_allclose(plan[:, -1, 2:], goals, atol=1e-4)
    assert finetune_config(params, task, 1, 0).steps == max(1, round(0.25 * task.pretrain.steps))


def test_a_phase_that_keeps_nothing_is_a_result_and_equals_its_control(
    phase1_root: tuple[Path, Params], tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """A discriminator that keeps nothing does not stop the run: one warning line, an empty selected file, and a
    phase 1 that trains on expert data only, exactly as its control (gain 0 by construction); evaluation, summary
    and report go through and say kept 0."""
    root, params = phase1_root
    copy = tmp_path / "project"
    shutil.copytree(root, copy)  # every stage below rewrites its outputs there
    strict = _with_phase1(params, max_error=1e-9)
    strict = dataclasses.replace(
        strict,
        tasks=(TASK,),
        unseen_tasks=(TASK,),
        collect_tasks=(TASK,),
        pretrain_tasks=(TASK,),
        phases=(strict.phase(1),),
    )
    report = run_discriminate(strict, TASK, copy, 1, progress=False)
    assert report["kept"] == 0 and report["rejected_tracking"] == report["generated"] == 16
    warning = [line for line in capfd.readouterr().err.splitlines() if line.startswith("warning:")]
    assert len(warning) == 1 and "kept none of 16 generated trajectories" in warning[0]
    selected = read_trajectories(copy / selected_path(TASK, 1, 0), env=TASK)
    assert len(selected) == 0 and selected.metadata["generator"]["stage"] == "discriminate"

    run_finetune(strict, TASK, copy, 1, CPU, progress=False)
    run_finetune(strict, TASK, copy, 1, CPU, progress=False, control=True)
    evolved = load_bundle(copy / model_dir(TASK, 1, 0))
    control = load_bundle(copy / model_dir(TASK, 1, 0, control=True))
    assert evolved.config["data"]["synthetic"] == {}
    pairs = zip(evolved.ema.parameters(), control.ema.parameters(), strict=True)
    assert all(torch.equal(a, b) for a, b in pairs)  # the same training, on the same data

    run_reference(strict, TASK, copy, progress=False)
    for k in (0, 1):
        run_evaluate(strict, TASK, copy, k, CPU, progress=False)
        run_evaluate_unseen(strict, TASK, copy, k, CPU, progress=False)
    gain = run_evaluate(strict, TASK, copy, 1, CPU, progress=False, control=True)
    assert gain["gain_mean"] == 0.0
    run_evaluate_unseen(strict, TASK, copy, 1, CPU, progress=False, control=True)
    summary = run_summarize(strict, copy)[TASK]["phase_1"]
    assert summary["discriminator"]["kept"] == 0 and summary["gain_mean"] == 0.0
    assert summary["score_mean"] == summary["control"]["score_mean"]
    assert summary["gold_coin"] == summary["control"]["gold_coin"]  # the same model on the unseen task too
    assert summary["unseen_gain"]["score"]["per_seed"] == {"0": 0.0}  # and no gain there, seed by seed
    run_report(copy)
    with (copy / "metrics" / "report" / TASK / "score_by_phase.csv").open() as f:
        rows = {row["phase"]: row for row in csv.DictReader(f)}
    assert float(rows["1"]["kept"]) == 0.0 and float(rows["1"]["gain_mean"]) == 0.0


def test_control_differs_from_its_phase_only_in_the_data(
    phase1_root: tuple[Path, Params], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The control trains phase 0's model with phase 1's steps, seed and settings on expert data only: training
    (deterministic in its inputs) gets the same starting weights, settings and optimizer state in both, and data
    that differ only by the phase's selected windows."""
    root, params = phase1_root
    out = run_finetune(params, TASK, root, 1, CPU, progress=False, control=True)
    assert out / "seed0" == root / model_dir(TASK, 1, 0, control=True) == root / f"models/{TASK}/phase1-control/seed0"
    control = load_bundle(out / "seed0")
    assert control.config["control"] is True and control.config["data"]["synthetic"] == {}
    evolved = load_bundle(root / model_dir(TASK, 1, 0))
    pairs = zip(control.diffusion.parameters(), evolved.diffusion.parameters(), strict=True)
    assert all(not torch.equal(a, b) for a, b in pairs)  # every tensor learned from the other data

    calls: list[dict] = []

    def record(bundle, dataset, cfg, device, **kwargs) -> list[tuple[int, float]]:
        weights = [p.detach().clone() for p in (*bundle.diffusion.parameters(), *bundle.ema.parameters())]
        calls.append({"weights": weights, "dataset": dataset, "cfg": cfg, "optimizer": kwargs["optimizer_state"]})
        return [(cfg.steps, 0.0)]

    monkeypatch.setattr(finetune_stage, "train", record)
    copy = tmp_path / "project"
    (copy / "models" / TASK).mkdir(parents=True)
    (copy / "data").symlink_to(root / "data")
    (copy / "models" / TASK / "phase0").symlink_to(root / "models" / TASK / "phase0")
    run_finetune(params, TASK, copy, 1, CPU, progress=False)
    run_finetune(params, TASK, copy, 1, CPU, progress=False, control=True)
    phase, ctrl = calls
    assert phase["cfg"] == ctrl["cfg"] == finetune_config(params, params.resolve(TASK), 1, 0)
    assert phase["optimizer"] is None and ctrl["optimizer"] is None  # both restart Adam
    assert all(torch.equal(a, b) for a, b in zip(phase["weights"], ctrl["weights"], strict=True))
    (expert, selected), (ctrl_expert,) = phase["dataset"].parts, ctrl["dataset"].parts
    assert np.array_equal(expert.data, ctrl_expert.data) and np.array_equal(expert.starts, ctrl_expert.starts)
    assert phase["dataset"].weights.tolist() == [0.5, 0.5] and ctrl["dataset"].weights.tolist() == [1.0]
    assert len(selected) > 0 and not np.array_equal(selected.data, expert.data)


def test_control_evaluation_reports_the_paired_gain(phase1_root: tuple[Path, Params]) -> None:
    root, params = phase1_root
    if not (root / model_dir(TASK, 1, 0, control=True)).exists():
        run_finetune(params, TASK, root, 1, CPU, progress=False, control=True)
    run_reference(params, TASK, root, progress=False)
    with pytest.raises(FileNotFoundError, match="phase 1's evaluation, needed for the gain"):
        run_evaluate(params, TASK, root, 1, CPU, progress=False, control=True)
    evolved = run_evaluate(params, TASK, root, 1, CPU, progress=False)
    control = run_evaluate(params, TASK, root, 1, CPU, progress=False, control=True)
    assert control["gain_mean"] == pytest.approx(evolved["score_mean"] - control["score_mean"])
    assert control["gain_n_episodes"] == evolved["n_episodes"] and control["gain_stderr"] >= 0.0
    assert control["n_seeds"] == 1 and control["stderr_over"] == "episodes"  # one training seed
    assert json.loads((root / phase_metrics_path(TASK, 1, control=True)).read_text()) == control
    assert (root / results_dir(TASK, 1, 0, control=True) / "episodes.parquet").exists()


@pytest.mark.parametrize("stage", ["evaluate", "evaluate-unseen"])
def test_an_evaluation_stopped_on_a_seed_takes_up_the_seeds_before_it(
    phase1_root: tuple[Path, Params], tmp_path: Path, capfd: pytest.CaptureFixture[str], stage: str
) -> None:
    """An evaluation stage that stops on its second training seed (whose model is missing) has recorded the first;
    run again once that model is there, after its outputs were removed (as DVC does), it plays only the second
    seed's episodes, puts the first seed's files back byte for byte with the same metrics, and leaves no record."""
    root, params = phase1_root
    copy = tmp_path / "project"
    shutil.copytree(root, copy)
    run_reference(params, TASK, copy, progress=False)
    two = dataclasses.replace(params, seeds=(0, 7))
    if stage == "evaluate":
        evaluate, outputs = run_evaluate, [results_dir(TASK, 0, 0), plots_dir(TASK, 0, 0)]
    else:
        evaluate, outputs = run_evaluate_unseen, [unseen_plots_dir(TASK, 0, 0)]
    with pytest.raises(FileNotFoundError):
        evaluate(two, TASK, copy, 0, CPU, progress=False)
    record = copy / seed_record_dir(TASK, stage, 0, 0)
    recorded = json.loads((record / "record.json").read_text())["metrics"]
    files = {p.relative_to(copy): p.read_bytes() for out in outputs for p in (copy / out).rglob("*") if p.is_file()}
    assert files and not (copy / seed_record_dir(TASK, stage, 0, 7)).exists()
    for out in outputs:
        shutil.rmtree(copy / out)
    shutil.copytree(copy / model_dir(TASK, 0, 0), copy / model_dir(TASK, 0, 7))
    capfd.readouterr()

    evaluate(two, TASK, copy, 0, CPU, progress=False)
    log = capfd.readouterr()
    assert (log.out + log.err).count("its results are taken up again") == 1
    again = {p.relative_to(copy): p.read_bytes() for out in outputs for p in (copy / out).rglob("*") if p.is_file()}
    assert again == files
    metrics_path = phase_metrics_path(TASK, 0) if stage == "evaluate" else unseen_metrics_path(TASK, 0)
    saved = json.loads((copy / metrics_path).read_text())
    assert saved["n_seeds"] == 2 and saved["seeds"]["0"] == recorded
    assert not record.exists() and not (copy / seed_record_dir(TASK, stage, 0, 7)).exists()

    # a record of another model is not taken up: the seed is played again, saying so
    other = dataclasses.replace(params, seeds=(0, 8))
    with pytest.raises(FileNotFoundError):
        evaluate(other, TASK, copy, 0, CPU, progress=False)
    shutil.rmtree(copy / model_dir(TASK, 0, 0))
    shutil.copytree(copy / model_dir(TASK, 1, 0), copy / model_dir(TASK, 0, 0))  # seed 0's phase 0 retrained
    capfd.readouterr()
    with pytest.raises(FileNotFoundError):
        evaluate(other, TASK, copy, 0, CPU, progress=False)
    log = capfd.readouterr()
    assert "written for other settings" in log.out + log.err and "taken up again" not in log.out + log.err
