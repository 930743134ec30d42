"""What git holds: code, configs, docs, small results and the few kept models of metrics/kept-models.json, never
generated data or training state (those live in DVC's cache); and a kept model still scores what it supports."""

from __future__ import annotations

import inspect
import re
import subprocess
from pathlib import Path

import pytest
import torch
from smoke_project import REPO
from typer.testing import CliRunner

from adaptdiffuser.checkpoint import load_bundle
from adaptdiffuser.cli import app
from adaptdiffuser.cli import evaluate_kept as cli_evaluate_kept
from adaptdiffuser.config.start_states import KEPT_EVAL_SEED, KEPT_HELD_OUT_SEED
from adaptdiffuser.errors import StageError
from adaptdiffuser.stages.kept_models import MANIFEST, evaluate_kept, evaluate_kept_seeds, load_manifest

GENERATED = (".parquet", ".npz", ".pkl", ".h5", ".hdf5")
KEPT_FILES = ("ema.pt", "normalizer.json", "config.json")


def tracked() -> list[str]:
    """The files git tracks in this repository at HEAD plus the index, less a stopped long run's carried resume state
    (``metrics/runs/<run>/carry/models/.resume/``: the least state that continues a run that cannot finish on the
    machine it runs on; the note of the commit that carries it says how many MB it adds)."""
    out = subprocess.run(["git", "ls-files"], cwd=REPO, check=True, capture_output=True, text=True).stdout
    return [f for f in out.splitlines() if not re.fullmatch(r"metrics/runs/[^/]+/carry/models/\.resume/[^/]+", f)]


def test_git_tracks_no_generated_data_or_training_state() -> None:
    files = tracked()
    assert files, "git ls-files listed nothing: not a git checkout?"
    generated = [f for f in files if f.endswith(GENERATED)]
    state = [f for f in files if "/.resume/" in f or Path(f).name.startswith("optimizer")]
    assert not generated and not state, f"tracked generated data {generated}, training state {state}"


def test_every_tracked_model_is_a_kept_model_of_the_manifest() -> None:
    manifest = load_manifest(REPO)
    listed = {f"{entry.path}/ema.pt" for entry in manifest.models.values()}
    models = {f for f in tracked() if f.endswith(".pt")}
    assert models == listed, f"not in {MANIFEST}: {sorted(models - listed)}; listed but untracked: {listed - models}"
    for name, entry in manifest.models.items():
        assert all((REPO / entry.path / file).is_file() for file in KEPT_FILES), name
        assert entry.control is None or manifest.models[entry.control].training_seed == entry.training_seed


def test_a_kept_model_loads_from_its_ema_weights_alone(tmp_path: Path) -> None:
    entry = load_manifest(REPO).models["maze2d-large/seed2/phase1-plans"]
    bundle = load_bundle(REPO / entry.path, ema_only=True)
    for raw, ema in zip(bundle.diffusion.model.parameters(), bundle.ema.model.parameters(), strict=True):
        assert torch.equal(raw, ema)
    with pytest.raises(FileNotFoundError, match="no model.pt"):
        load_bundle(REPO / entry.path)


def test_a_kept_model_scores_what_it_supports_on_its_evaluation_episodes() -> None:
    """Seed 2's plans-recipe phase-1 model and its control on the science runs' 50 episodes (seed 1000): the
    committed per-seed numbers (exactly on the CPU kind that made them; the tolerance covers another CPU's last
    digits, far below the 7-point gap between the two models)."""
    name = "maze2d-large/seed2/phase1-plans"
    supports = load_manifest(REPO).models[name].supports
    out = evaluate_kept(REPO, name, episodes=50, eval_seed=1000, device=torch.device("cpu"))
    assert out["model"]["n_episodes"] == 50 and out["gain"]["gain_n_episodes"] == 50
    assert out["model"]["score_mean"] == pytest.approx(supports["score_mean"], abs=1.0)
    assert out["gain"]["gain_mean"] == pytest.approx(supports["gain_mean"], abs=1.0)
    control = load_manifest(REPO).models["maze2d-large/seed2/phase1-control"].supports
    assert out["control"]["score_mean"] == pytest.approx(control["score_mean"], abs=1.0)


def test_kept_models_of_several_seeds_play_their_own_start_states_and_give_an_interval() -> None:
    names = ["maze2d-large/seed0/phase1-rollouts", "maze2d-large/seed1/phase1-rollouts"]
    cpu = torch.device("cpu")
    out = evaluate_kept_seeds(REPO, names, episodes=4, eval_seed=3000, device=cpu)
    assert out["eval_seeds"] == {names[0]: 3000, names[1]: 3001}
    alone = evaluate_kept(REPO, names[1], episodes=4, eval_seed=3001, device=cpu)
    assert out["models"][names[1]]["episode_scores"] == alone["episode_scores"]
    gain = out["interval"]["gain"]
    assert (gain["n_seeds"], gain["n_episodes"]) == (2, 4) and gain["ci_low"] <= gain["mean"] <= gain["ci_high"]
    assert gain["over"] == "seeds" and 0.0 <= gain["win_rate"] <= 1.0 and "probability_of_improvement" not in gain
    same = evaluate_kept_seeds(
        REPO, names, episodes=4, eval_seed=3000, device=cpu, own_start_states=False, held_out_seed=7000,
        held_out_episodes=2,
    )  # fmt: skip
    assert same["eval_seeds"] == {names[0]: 3000, names[1]: 3000}
    held_out = same["held_out"]
    assert held_out["eval_seeds"] == {names[0]: 7000, names[1]: 7000} and held_out["episodes"] == 2
    assert held_out["interval"]["gain"]["n_episodes"] == 2 and "win_rate" in held_out["models"][names[0]]["gain"]


def test_evaluate_kept_defaults_to_start_states_no_other_part_plays() -> None:
    """Its own and held-out defaults are config/start_states.py's, which the config check keeps apart from the
    pipeline's and the sweep's; a held-out set that meets the own one is refused before anything plays."""
    defaults = {p.name: p.default for p in inspect.signature(cli_evaluate_kept).parameters.values()}
    assert (defaults["eval_seed"], defaults["held_out_seed"]) == (KEPT_EVAL_SEED, KEPT_HELD_OUT_SEED)
    with pytest.raises(StageError, match="choose held-out start states that are others"):
        names = ["maze2d-large/seed0/phase1-rollouts", "maze2d-large/seed1/phase1-rollouts"]
        evaluate_kept_seeds(REPO, names, 4, 3001, torch.device("cpu"), held_out_seed=3000)


def test_evaluate_kept_refuses_an_unknown_model_in_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)
    result = CliRunner().invoke(app, ["evaluate-kept", "maze2d-large/seed9/phase1", "--episodes", "1"])
    assert result.exit_code == 2
    assert "no such kept model" in result.output and len(result.output.strip().splitlines()) == 1
