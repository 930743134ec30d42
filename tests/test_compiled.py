"""The compiled fast path (``compile.training`` / ``compile.sampling``): the same function as the eager network
within float rounding, for Mish alone, for sampling plans and for training steps; checkpoints unchanged."""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from adaptdiffuser.checkpoint import load_bundle, make_bundle, save_bundle
from adaptdiffuser.config import ConfigError, DiffusionParams, ModelParams, Params, PretrainParams
from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.data.windows import WindowDataset
from adaptdiffuser.diffusion.samplers import make_sampler
from adaptdiffuser.models.compiled import compile_network, is_unfinished_library, remove_unfinished_libraries
from adaptdiffuser.models.unet import Mish
from adaptdiffuser.planning import Planner
from adaptdiffuser.training import train

CPU = torch.device("cpu")
TRAIN = PretrainParams(steps=6, batch_size=4, lr=1e-3, ema_every=2, ema_start=2, log_every=1, seed=3)


def test_mish_eager_is_aten_and_compiled_form_is_equal_within_rounding() -> None:
    x = torch.cat([torch.linspace(-60, 60, 4001), torch.tensor([-1e4, 1e4, 19.9, 20.0, 20.1, 0.0])])
    mish = Mish()
    assert torch.equal(mish(x), torch.nn.functional.mish(x))  # eagerly: aten's kernel itself

    compiled = torch.compile(lambda v: mish(v), fullgraph=True)
    xg = x.clone().requires_grad_(True)
    out = compiled(xg)
    (grad,) = torch.autograd.grad(out.sum(), xg)
    xr = x.clone().requires_grad_(True)
    ref = torch.nn.functional.mish(xr)
    (ref_grad,) = torch.autograd.grad(ref.sum(), xr)
    assert torch.isfinite(out).all() and torch.isfinite(grad).all()
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(grad, ref_grad, rtol=1e-5, atol=1e-5)


@pytest.fixture
def bundle_dir(
    tmp_path, normalizer: MinMaxNormalizer, tiny_model_params: ModelParams, tiny_diffusion_params: DiffusionParams
):
    torch.manual_seed(0)
    path = tmp_path / "bundle"
    save_bundle(path, make_bundle(tiny_model_params, tiny_diffusion_params, 4, 2, normalizer))
    return path


def test_compiled_planner_samples_the_eager_plans(bundle_dir, expert_traj) -> None:
    states = expert_traj.observation[:6]
    goals = expert_traj.observation[10:16]
    plans = {}
    for compiled in (False, True):
        bundle = load_bundle(bundle_dir)
        planner = Planner(bundle, make_sampler("ddim", 4), CPU, compiled=compiled)
        plans[compiled] = [planner.plan(states[:n], goals[:n], list(range(n))) for n in (6, 3)]  # two batch sizes
        assert set(bundle.ema.state_dict()) == set(load_bundle(bundle_dir).ema.state_dict())
    for eager, fast in zip(plans[False], plans[True], strict=True):
        np.testing.assert_allclose(fast, eager, rtol=1e-4, atol=1e-4)


def test_compiled_network_has_the_eager_gradients(bundle_dir, dataset: WindowDataset) -> None:
    x0 = torch.from_numpy(dataset.sample(8, np.random.default_rng(0)))
    cond = {0: x0[:, 0, 2:]}
    grads = {}
    for compiled in (False, True):
        model = load_bundle(bundle_dir).diffusion.train()
        if compiled:
            compile_network(model.model, CPU, "compile.training")
        model.loss(x0, cond, generator=torch.Generator().manual_seed(0)).backward()
        grads[compiled] = {name: p.grad for name, p in model.named_parameters()}
    for name, grad in grads[False].items():
        torch.testing.assert_close(grads[True][name], grad, rtol=1e-3, atol=1e-6, msg=name)


def test_compiled_training_follows_the_eager_run_and_saves_the_same_checkpoint(
    bundle_dir, tmp_path, dataset: WindowDataset
) -> None:
    histories = {}
    for compiled in (False, True):
        bundle = load_bundle(bundle_dir)
        histories[compiled] = train(bundle, dataset, TRAIN, CPU, progress=False, compiled=compiled)
        save_bundle(tmp_path / f"trained-{compiled}", bundle)
    eager, fast = histories[False], histories[True]
    assert [s for s, _ in fast] == [s for s, _ in eager] and len(eager) == TRAIN.steps
    # Adam turns rounding-level gradients of weights that barely matter into full-size steps, so the runs are
    # compared by their losses (the same batches and noise) rather than weight by weight
    np.testing.assert_allclose([v for _, v in fast], [v for _, v in eager], rtol=1e-3)
    plain, trained = load_bundle(tmp_path / "trained-False"), load_bundle(tmp_path / "trained-True")
    assert trained.diffusion.state_dict().keys() == plain.diffusion.state_dict().keys()
    assert trained.optimizer is not None and trained.optimizer.keys() == plain.optimizer.keys()


def test_compiling_without_a_cpp_compiler_names_the_setting(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))  # an empty folder: no g++, c++ or clang++
    monkeypatch.delenv("CXX", raising=False)
    with pytest.raises(ConfigError, match="compile.sampling: true needs a C\\+\\+ compiler"):
        compile_network(torch.nn.Linear(2, 2), CPU, "compile.sampling")


def test_compile_settings_are_validated_params_off_by_default_in_the_library() -> None:
    assert Params().compile.training is False  # the library's default; the profiles choose (docs/speed.md)
    with pytest.raises((ConfigError, ValueError), match="compile"):
        Params(compile={"training": "sometimes"})
    assert dataclasses.asdict(Params(compile={"sampling": True}).compile) == {"training": False, "sampling": True}


COMPILE_PROBE = """
import sys, torch
from torch import nn
from adaptdiffuser.models.compiled import compile_network


class Net(nn.Module):
    def __init__(self):
        super().__init__()
        self.a, self.n, self.b = nn.Conv1d(4, 8, 5, padding=2), nn.GroupNorm(2, 8), nn.Conv1d(8, 4, 5, padding=2)

    def forward(self, x):
        return self.b(nn.functional.mish(self.n(self.a(x))))


torch.manual_seed(0)
net, x = Net(), torch.randn(3, 4, 16)
with torch.no_grad():
    eager = net(x)
    if sys.argv[1] == "project":
        compile_network(net, torch.device("cpu"), "compile.sampling")
    else:
        net.compile()
    print("max difference", float((net(x) - eager).abs().max()))
"""


def _compile_in_process(tmp_path: Path, how: str) -> subprocess.CompletedProcess[str]:
    script = tmp_path / "probe.py"
    script.write_text(COMPILE_PROBE)
    env = dict(os.environ, TORCHINDUCTOR_CACHE_DIR=str(tmp_path / "cache"), OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, str(script), how], env=env, capture_output=True, text=True)


def test_a_compile_cache_poisoned_by_a_killed_compile_heals(tmp_path: Path) -> None:
    """A process killed while inductor writes a kernel leaves it cut short; plain ``torch.compile`` then fails in
    every later process, the project's compile removes the unfinished kernels and compiles again."""
    first = _compile_in_process(tmp_path, "project")
    assert first.returncode == 0, first.stderr[-2000:]
    libraries = sorted((tmp_path / "cache").rglob("*.so"))
    assert libraries and not any(is_unfinished_library(path) for path in libraries)

    def poison() -> None:
        for path in libraries:  # what a kill leaves: the files exist, their contents never came
            path.write_bytes(b"")

    poison()
    plain = _compile_in_process(tmp_path, "plain")
    assert plain.returncode != 0  # the poison is real: torch alone does not recover
    poison()
    healed = _compile_in_process(tmp_path, "project")
    assert healed.returncode == 0, healed.stderr[-2000:]
    assert f"removed {len(libraries)} unfinished compiled kernels" in healed.stderr
    assert float(healed.stdout.split("max difference")[-1]) < 1e-5
    assert not any(is_unfinished_library(path) for path in (tmp_path / "cache").rglob("*.so"))


def test_unfinished_libraries_are_told_from_whole_ones(tmp_path: Path) -> None:
    whole = Path(torch.__file__).parent / "lib" / "libc10.so"
    assert not is_unfinished_library(whole)
    cut = tmp_path / "cache" / "ab" / "cut.so"
    cut.parent.mkdir(parents=True)
    data = whole.read_bytes()
    cut.write_bytes(data[: len(data) // 2])  # the header is there, the sections it names are not
    empty = tmp_path / "cache" / "empty.so"
    empty.write_bytes(b"")
    kept = tmp_path / "cache" / "whole.so"
    shutil.copy2(whole, kept)
    assert is_unfinished_library(cut) and is_unfinished_library(empty)
    assert remove_unfinished_libraries(tmp_path / "cache") == [cut, empty]
    assert kept.exists() and not cut.exists() and not empty.exists()
