"""Adam state in model bundles, and fine-tuning that restarts Adam (the default) or carries phase k-1's on."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from adaptdiffuser.checkpoint import BUNDLE_FILES, OPTIMIZER_FILE, ModelBundle, load_bundle, make_bundle, save_bundle
from adaptdiffuser.config import DiffusionParams, ModelParams, PretrainParams
from adaptdiffuser.config.sections import FinetuneParams
from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.data.windows import WindowDataset
from adaptdiffuser.training import adam_steps, carried_optimizer, train

CPU = torch.device("cpu")
PRETRAIN = PretrainParams(steps=20, batch_size=4, lr=1e-3, ema_every=5, ema_start=10, log_every=1, seed=3)
# as the fine-tune stage derives it: pretrain's settings, another seed, the EMA continued from the first step
FINETUNE = dataclasses.replace(PRETRAIN, steps=10, seed=11, ema_start=0, checkpoint_every=5)
BETAS = (0.9, 0.999)  # torch.optim.Adam's defaults, which training uses


class Interrupted(Exception):
    """Stands in for the stage being killed part-way."""


@pytest.fixture(scope="module")
def phase0(
    tmp_path_factory: pytest.TempPathFactory,
    dataset: WindowDataset,
    normalizer: MinMaxNormalizer,
    tiny_model_params: ModelParams,
    tiny_diffusion_params: DiffusionParams,
) -> Path:
    """A pretrained bundle on disk (with its optimizer.pt)."""
    torch.manual_seed(0)
    bundle = make_bundle(tiny_model_params, tiny_diffusion_params, 4, 2, normalizer, phase=0)
    train(bundle, dataset, PRETRAIN, CPU, progress=False)
    out = tmp_path_factory.mktemp("models") / "phase0"
    save_bundle(out, bundle)
    return out


@pytest.fixture(scope="module")
def old_phase0(phase0: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same bundle as saved before optimizer states were kept: no optimizer.pt."""
    out = tmp_path_factory.mktemp("old") / "phase0"
    bundle = load_bundle(phase0)
    bundle.optimizer = None
    save_bundle(out, bundle)
    return out


def same_raw_weights(a: ModelBundle, b: ModelBundle) -> bool:
    wa, wb = a.diffusion.model.state_dict(), b.diffusion.model.state_dict()
    return wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


FineTune = Callable[..., tuple[ModelBundle, list[tuple[int, float]]]]


@pytest.fixture
def fine_tune(dataset: WindowDataset) -> FineTune:
    """Fine-tune the bundle saved at ``source`` as the stage does: load it, then train with the ``mode``'s Adam."""

    def run(source: Path, mode: str, cfg: PretrainParams = FINETUNE) -> tuple[ModelBundle, list[tuple[int, float]]]:
        bundle = load_bundle(source)
        state = carried_optimizer(bundle, mode)
        return bundle, train(bundle, dataset, cfg, CPU, progress=False, optimizer_state=state)

    return run


def test_trained_bundle_round_trips_its_adam_state(phase0: Path) -> None:
    assert sorted(p.name for p in phase0.iterdir()) == sorted([*BUNDLE_FILES, OPTIMIZER_FILE])
    loaded = load_bundle(phase0)
    record = loaded.optimizer
    assert record is not None and record["step"] == PRETRAIN.steps == adam_steps(record["adam"])
    params = list(loaded.diffusion.model.parameters())
    state = record["adam"]["state"]
    assert len(state) == len(params)
    for i, p in enumerate(params):
        assert state[i]["exp_avg"].shape == p.shape and state[i]["exp_avg"].abs().sum() > 0
        assert int(state[i]["step"]) == PRETRAIN.steps
    assert record["adam"]["param_groups"][0]["lr"] == PRETRAIN.lr

    # saved again and reloaded: the same tensors
    again = phase0.parent / "again"
    save_bundle(again, loaded)
    reloaded = load_bundle(again).optimizer
    assert reloaded is not None and reloaded["step"] == record["step"]
    for i in state:
        for key, value in state[i].items():
            assert torch.equal(reloaded["adam"]["state"][i][key], value)


def test_untrained_and_old_bundles_have_no_optimizer_and_still_load(
    old_phase0: Path,
    tmp_path: Path,
    tiny_model_params: ModelParams,
    tiny_diffusion_params: DiffusionParams,
    normalizer: MinMaxNormalizer,
) -> None:
    fresh = make_bundle(tiny_model_params, tiny_diffusion_params, 4, 2, normalizer)
    save_bundle(tmp_path / "fresh", fresh)
    assert sorted(p.name for p in (tmp_path / "fresh").iterdir()) == sorted(BUNDLE_FILES)
    assert load_bundle(tmp_path / "fresh").optimizer is None
    assert not (old_phase0 / OPTIMIZER_FILE).exists() and load_bundle(old_phase0).optimizer is None


def test_carry_from_an_old_bundle_says_adam_restarts(old_phase0: Path, capsys: pytest.CaptureFixture) -> None:
    bundle = load_bundle(old_phase0)
    assert carried_optimizer(bundle, "restart") is None
    assert capsys.readouterr().out == ""  # nothing to say when restarting anyway
    assert carried_optimizer(bundle, "carry", "models/x/phase0") is None
    out = capsys.readouterr().out
    assert "models/x/phase0" in out and "no saved optimizer state" in out and "Adam restarts" in out


def test_unknown_mode_is_rejected(phase0: Path) -> None:
    with pytest.raises(ValueError, match="restart"):
        carried_optimizer(load_bundle(phase0), "keep")
    with pytest.raises(ValueError, match="must be one of 'restart', 'carry'"):
        FinetuneParams(optimizer="keep")
    assert FinetuneParams().optimizer == "restart"


def test_restart_ignores_a_saved_optimizer_state(phase0: Path, old_phase0: Path, fine_tune: FineTune) -> None:
    """``restart`` is the training as it was before optimizer states were saved: same losses, same weights."""
    new, new_history = fine_tune(phase0, "restart")
    old, old_history = fine_tune(old_phase0, "restart")
    assert new_history == old_history
    assert same_raw_weights(new, old)
    assert new.optimizer is not None and new.optimizer["step"] == FINETUNE.steps  # a fresh count


def test_carry_continues_the_adam_moments_and_step(phase0: Path, fine_tune: FineTune) -> None:
    """One step from the same weights and batch: the carried moments are those of phase 0 decayed once, plus the
    same gradient term a fresh Adam gets; the step count (and so the bias correction) continues."""
    one = dataclasses.replace(FINETUNE, steps=1)
    start = load_bundle(phase0).optimizer
    assert start is not None
    carried, _ = fine_tune(phase0, "carry", one)
    restarted, _ = fine_tune(phase0, "restart", one)
    assert carried.optimizer is not None and restarted.optimizer is not None
    assert carried.optimizer["step"] == PRETRAIN.steps + 1 and restarted.optimizer["step"] == 1
    b1, b2 = BETAS
    for i, s0 in start["adam"]["state"].items():
        c, r = carried.optimizer["adam"]["state"][i], restarted.optimizer["adam"]["state"][i]
        # fresh Adam after one step: (1 - b1) g and (1 - b2) g^2; carried: the decayed phase-0 moments added
        torch.testing.assert_close(c["exp_avg"], b1 * s0["exp_avg"] + r["exp_avg"])
        torch.testing.assert_close(c["exp_avg_sq"], b2 * s0["exp_avg_sq"] + r["exp_avg_sq"])
        assert not torch.equal(c["exp_avg"], r["exp_avg"])
    # the saved record was not updated in place by the run that carried it
    assert load_bundle(phase0).optimizer["step"] == PRETRAIN.steps  # type: ignore[index]


def test_carry_is_deterministic_and_differs_from_restart(phase0: Path, fine_tune: FineTune) -> None:
    a, history_a = fine_tune(phase0, "carry")
    b, history_b = fine_tune(phase0, "carry")
    assert history_a == history_b
    assert same_raw_weights(a, b)
    assert a.optimizer is not None and a.optimizer["step"] == PRETRAIN.steps + FINETUNE.steps
    _, restarted = fine_tune(phase0, "restart")
    assert restarted[0] == history_a[0]  # the first loss is computed before any update
    assert restarted[1:] != history_a[1:]


def test_carry_uses_this_runs_learning_rate(phase0: Path, fine_tune: FineTune) -> None:
    bundle, _ = fine_tune(phase0, "carry", dataclasses.replace(FINETUNE, steps=2, lr=5e-4))
    assert bundle.optimizer is not None
    assert [g["lr"] for g in bundle.optimizer["adam"]["param_groups"]] == [5e-4]


def test_killed_and_resumed_carry_run_matches_straight(
    phase0: Path, tmp_path: Path, dataset: WindowDataset, fine_tune: FineTune
) -> None:
    straight, straight_history = fine_tune(phase0, "carry")
    resume = tmp_path / "resume.pt"

    def kill_at_8(step: int, loss: float) -> None:
        if step == 8:
            raise Interrupted

    bundle = load_bundle(phase0)
    with pytest.raises(Interrupted):
        train(
            bundle,
            dataset,
            FINETUNE,
            CPU,
            resume,
            "run",
            on_log=kill_at_8,
            progress=False,
            optimizer_state=carried_optimizer(bundle, "carry"),
        )
    bundle = load_bundle(phase0)
    history = train(
        bundle,
        dataset,
        FINETUNE,
        CPU,
        resume,
        "run",
        progress=False,
        optimizer_state=carried_optimizer(bundle, "carry"),
    )
    assert history == straight_history
    assert same_raw_weights(bundle, straight)
    assert bundle.optimizer is not None and bundle.optimizer["step"] == straight.optimizer["step"]  # type: ignore[index]
