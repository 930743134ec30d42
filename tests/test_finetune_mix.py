"""Fine-tuning batches mix the expert data with the data selected in a phase and its ancestors in the declared shares:
``finetune.expert_weight`` expert, the rest split evenly over the lineage's phases (no other phase). Real Parquet
files whose trajectories carry their source as a marker value; the stage builds its dataset as it does in the
pipeline (training itself is replaced by a recorder), and many batches drawn from that dataset's own sampler must
show each source's share within a binomial tolerance."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import adaptdiffuser.stages.finetune as finetune
from adaptdiffuser.checkpoint import make_bundle, save_bundle
from adaptdiffuser.config import DiffusionParams, EvolutionParams, FinetuneParams, ModelParams, Params, PretrainParams
from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.data.schema import Trajectories, make_metadata, write_trajectories
from adaptdiffuser.data.windows import MixedWindowDataset, WindowDataset, joint_array
from adaptdiffuser.layout import dataset_path, model_dir, selected_path

TASK = "maze2d-umaze"
ACT = 2
HORIZON = 32
BATCH = 32
N_BATCHES = 2000
Z = 4.5  # tolerance in binomial standard errors
# phase 3 starts from phase 1 (phase 2 is a side branch), phase 4 from phase 3: phase 4's lineage is [1, 3, 4]
PHASES = {"phase1": {"previous": 0}, "phase2": {"previous": 1}, "phase3": {"previous": 1}, "phase4": {"previous": 3}}


def marked(marker: float, episodes: int, length: int, source: str) -> Trajectories:
    """Episodes whose first observation column holds ``marker`` at every step (the other columns vary)."""
    n = episodes * length
    obs = np.zeros((n, 4), dtype=np.float32)
    obs[:, 0] = marker
    obs[:, 1] = np.tile(np.linspace(-1.0, 1.0, length), episodes)
    return Trajectories(
        episode_id=np.repeat(np.arange(episodes), length),
        step=np.tile(np.arange(length), episodes),
        observation=obs,
        action=np.zeros((n, ACT), dtype=np.float32),
        reward=np.zeros(n, dtype=np.float32),
        terminal=np.zeros(n, dtype=bool),
        timeout=np.zeros(n, dtype=bool),
        metadata=make_metadata(TASK, 4, ACT, source, {}),
    )


NORMALIZER = MinMaxNormalizer(low=[-1, -1, 0, -1, -1, -1], high=[1, 1, 40, 1, 1, 1])


def sources(batch: np.ndarray) -> np.ndarray:
    """The marker of each window of a normalized batch: 0 for expert windows, 10 j for phase j's."""
    return np.rint(NORMALIZER.unnormalize(batch.astype(np.float64))[:, 0, ACT]).astype(int)


def observed_shares(dataset: MixedWindowDataset, markers: list[int], seed: int = 0) -> tuple[np.ndarray, list]:
    """Each marker's share of ``N_BATCHES`` batches of ``BATCH`` windows, and each batch's per-marker counts."""
    rng = np.random.default_rng(seed)
    per_batch = []
    for _ in range(N_BATCHES):
        found = sources(dataset.sample(BATCH, rng))
        assert set(found.tolist()) <= set(markers), f"a window from an unexpected source: {set(found.tolist())}"
        per_batch.append([int((found == m).sum()) for m in markers])
    counts = np.asarray(per_batch)
    return counts.sum(0) / counts.sum(), per_batch


def assert_shares(observed: np.ndarray, declared: list[float]) -> None:
    """Observed shares within ``Z`` binomial standard errors of the declared ones (exact for shares 0 and 1)."""
    n = N_BATCHES * BATCH
    for got, p in zip(observed, declared, strict=True):
        assert abs(got - p) <= Z * np.sqrt(p * (1 - p) / n), (observed, declared)


@pytest.fixture
def project(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, Params, dict]:
    """A project folder with expert data (marker 0), every phase's selected data (marker 10 j) and phase 3's model;
    the fine-tune stage's training, tracking and pictures are replaced by a recorder of what it trains on."""
    params = Params(
        model=ModelParams(dim=8, dim_mults=[1, 2]),
        diffusion=DiffusionParams(horizon=HORIZON),
        pretrain=PretrainParams(batch_size=BATCH),
        evolution=EvolutionParams(finetune=FinetuneParams(expert_weight=0.4)),
        phases=PHASES,
    )
    write_trajectories(tmp_path / dataset_path(TASK), marked(0.0, 6, 40, "expert"))
    for j in range(1, 5):
        write_trajectories(tmp_path / selected_path(TASK, j, 0), marked(10.0 * j, 2 + j, 36, "synthetic"))
    task = params.resolve(TASK)
    bundle = make_bundle(task.model, task.diffusion, 4, ACT, NORMALIZER, task=TASK, phase=3)
    save_bundle(tmp_path / model_dir(TASK, 3, 0), bundle)

    seen: dict = {}

    def record(bundle, dataset, cfg, device, **kwargs) -> list[tuple[int, float]]:
        seen.update(dataset=dataset, cfg=cfg)
        return [(cfg.steps, 0.0)]

    monkeypatch.setattr(finetune, "train", record)
    monkeypatch.setattr(finetune, "save_loss_curve", lambda *args, **kwargs: None)
    return tmp_path, params, seen


def test_finetune_batches_hold_expert_and_each_ancestor_in_the_declared_shares(project) -> None:
    root, params, seen = project
    assert params.lineage(4) == [1, 3, 4]
    finetune.finetune_seed(params, TASK, root, 4, torch.device("cpu"), 0, progress=False)
    dataset, cfg = seen["dataset"], seen["cfg"]
    assert cfg.batch_size == BATCH
    markers = [0, 10, 20, 30, 40]  # expert, phases 1..4
    declared = [0.4, 0.2, 0.0, 0.2, 0.2]  # expert_weight, then (1 - 0.4) / 3 for each of phases 1, 3 and 4
    shares, per_batch = observed_shares(dataset, markers)
    assert_shares(shares, declared)
    # and every batch holds each source's share rounded down or up (no batch without a source of the mix)
    for counts in per_batch:
        for count, p in zip(counts, declared, strict=True):
            assert np.floor(p * BATCH) <= count <= np.ceil(p * BATCH), (counts, declared)


def test_control_batches_are_all_expert(project) -> None:
    root, params, seen = project
    finetune.finetune_seed(params, TASK, root, 4, torch.device("cpu"), 0, progress=False, control=True)
    shares, _ = observed_shares(seen["dataset"], [0, 10, 20, 30, 40])
    assert shares.tolist() == [1.0, 0.0, 0.0, 0.0, 0.0]


@pytest.mark.parametrize(
    ("weights", "batch"),
    [([1.0, 1.0], 32), ([3.0, 1.0], 7), ([1.0, 1.0, 1.0], 32), ([0.5, 1 / 6, 1 / 6, 1 / 6], 32), ([0.3, 0.7], 5)],
)
def test_mixed_dataset_draws_each_part_in_its_share(weights: list[float], batch: int) -> None:
    """The sampler itself, for shares that a batch cannot hold exactly: over many batches each part still gets its
    share, and every batch holds each part's share of the batch rounded down or up."""
    parts = [WindowDataset(marked(10.0 * i, 3, 40, "expert"), HORIZON, NORMALIZER) for i in range(len(weights))]
    mixed = MixedWindowDataset(parts, weights)
    declared = np.asarray(weights) / sum(weights)
    rng = np.random.default_rng(1)
    counts = np.zeros((N_BATCHES, len(weights)), dtype=int)
    for b in range(N_BATCHES):
        found = sources(mixed.sample(batch, rng))
        assert len(found) == batch
        counts[b] = [(found == 10 * i).sum() for i in range(len(weights))]
    n = N_BATCHES * batch
    shares = counts.sum(0) / n
    assert np.all(np.abs(shares - declared) <= Z * np.sqrt(declared * (1 - declared) / n)), (shares, declared)
    assert np.all(counts >= np.floor(declared * batch)) and np.all(counts <= np.ceil(declared * batch))


def test_joint_array_marker_survives_the_windows() -> None:
    """The marker is what the tests above read back: a window of phase j's data decodes to 10 j at every step."""
    traj = marked(30.0, 2, 40, "synthetic")
    assert (joint_array(traj)[:, ACT] == 30.0).all()
    batch = WindowDataset(traj, HORIZON, NORMALIZER).sample(5, np.random.default_rng(0))
    decoded = NORMALIZER.unnormalize(batch.astype(np.float64))[..., ACT]
    np.testing.assert_allclose(decoded, 30.0, atol=1e-4)


def test_whole_shares_draw_no_randomness_for_the_rounding() -> None:
    """When every share is a whole number of windows, the counts are fixed and the random stream is left alone, so
    such mixes (the pipeline's 0.5 / 0.25 / 0.25 of 32) draw the same windows as they always did."""
    parts = [WindowDataset(marked(10.0 * i, 3, 40, "expert"), HORIZON, NORMALIZER) for i in range(3)]
    mixed = MixedWindowDataset(parts, [0.5, 0.25, 0.25])
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert mixed.counts(BATCH, rng) == [16, 8, 8]
    assert rng.bit_generator.state == state
