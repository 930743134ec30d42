"""Model bundles on disk, and the training loop's resumable checkpoints on real expert data."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

import adaptdiffuser.training as training
from adaptdiffuser.checkpoint import BUNDLE_FILES, ModelBundle, load_bundle, make_bundle, save_bundle
from adaptdiffuser.config import DiffusionParams, ModelParams, PretrainParams
from adaptdiffuser.data.normalizer import MinMaxNormalizer
from adaptdiffuser.data.schema import Trajectories
from adaptdiffuser.data.windows import WindowDataset
from adaptdiffuser.diffusion.noise import RowNoise
from adaptdiffuser.diffusion.samplers import DDIMSampler
from adaptdiffuser.training import fingerprint, train

CPU = torch.device("cpu")
CFG = PretrainParams(
    steps=30, batch_size=4, lr=1e-3, ema_every=5, ema_start=10, log_every=5, checkpoint_every=10, seed=3
)


class Interrupted(Exception):
    """Stands in for the stage being killed part-way."""


@pytest.fixture
def new_bundle(tiny_model_params: ModelParams, tiny_diffusion_params: DiffusionParams, normalizer: MinMaxNormalizer):
    def build(seed: int = 0) -> ModelBundle:
        torch.manual_seed(seed)
        return make_bundle(tiny_model_params, tiny_diffusion_params, 4, 2, normalizer, task="maze2d-umaze", phase=0)

    return build


def weights(bundle: ModelBundle) -> dict[str, dict[str, torch.Tensor]]:
    return {
        "model": {k: v.clone() for k, v in bundle.diffusion.model.state_dict().items()},
        "ema": {k: v.clone() for k, v in bundle.ema.model.state_dict().items()},
    }


def assert_same_weights(a: dict, b: dict) -> None:
    for part in ("model", "ema"):
        assert a[part].keys() == b[part].keys()
        for key in a[part]:
            assert torch.equal(a[part][key], b[part][key]), f"{part}.{key} differs"


def test_dataset_from_expert_stream(expert_traj: Trajectories, dataset: WindowDataset) -> None:
    assert len(expert_traj) == 3000 and len(expert_traj.episodes()) > 1
    assert len(dataset) > 100 and dataset.act_dim == 2
    batch = dataset.sample(8, np.random.default_rng(0))
    assert batch.shape == (8, 16, 6) and batch.dtype == np.float32
    assert batch.min() >= -1.0 - 1e-6 and batch.max() <= 1.0 + 1e-6
    # windows never cross an episode boundary
    ids = expert_traj.episode_id
    assert all(ids[s] == ids[s + 15] for s in dataset.starts)


def test_window_dataset_needs_long_enough_episodes(expert_traj: Trajectories, normalizer: MinMaxNormalizer) -> None:
    with pytest.raises(ValueError, match="horizon=5000"):
        WindowDataset(expert_traj, 5000, normalizer)


def test_bundle_round_trip_gives_identical_outputs(tmp_path: Path, new_bundle) -> None:
    bundle = new_bundle(0)
    with torch.no_grad():  # make the EMA weights differ from the raw ones
        for p in bundle.ema.parameters():
            p.add_(0.05 * torch.randn_like(p))
    save_bundle(tmp_path / "phase0", bundle)
    assert sorted(p.name for p in (tmp_path / "phase0").iterdir()) == sorted(BUNDLE_FILES)

    loaded = load_bundle(tmp_path / "phase0")
    assert loaded.config == bundle.config and loaded.config["phase"] == 0
    assert loaded.normalizer.state_dict() == bundle.normalizer.state_dict()
    x = torch.randn(3, 16, 6)
    t = torch.tensor([0, 4, 7])
    with torch.no_grad():
        assert torch.equal(loaded.ema.model(x, t), bundle.ema.model(x, t))
        assert torch.equal(loaded.diffusion.model(x, t), bundle.diffusion.model(x, t))
        assert not torch.allclose(loaded.ema.model(x, t), loaded.diffusion.model(x, t))
    cond = {0: x[:, 0, 2:], 15: x[:, -1, 2:]}
    sampler = DDIMSampler(4)
    a = sampler.sample(loaded.ema.eval(), cond, RowNoise([1, 2, 3]))
    b = sampler.sample(bundle.ema.eval(), cond, RowNoise([1, 2, 3]))
    assert torch.equal(a, b)


def test_save_bundle_replaces_existing_directory(tmp_path: Path, new_bundle) -> None:
    out = tmp_path / "phase0"
    save_bundle(out, new_bundle(0))
    second = new_bundle(1)
    save_bundle(out, second)
    loaded = load_bundle(out)
    for k, v in second.ema.model.state_dict().items():
        assert torch.equal(loaded.ema.model.state_dict()[k], v)
    assert [p.name for p in tmp_path.iterdir()] == ["phase0"]  # no temporary or old directories left


def test_load_bundle_missing_ema_names_the_file(tmp_path: Path, new_bundle) -> None:
    save_bundle(tmp_path / "phase0", new_bundle(0))
    (tmp_path / "phase0" / "ema.pt").unlink()
    with pytest.raises(FileNotFoundError, match="ema.pt"):
        load_bundle(tmp_path / "phase0")
    with pytest.raises(FileNotFoundError, match="model.pt"):
        load_bundle(tmp_path / "never-trained")


def test_train_reduces_loss_and_keeps_ema(dataset: WindowDataset, new_bundle) -> None:
    bundle = new_bundle(0)
    cfg = dataclasses.replace(CFG, steps=60, log_every=20)
    history = train(bundle, dataset, cfg, CPU, progress=False)
    assert [s for s, _ in history] == [20, 40, 60]
    assert all(np.isfinite(loss) for _, loss in history)
    assert history[-1][1] < history[0][1]
    ema, raw = bundle.ema.model.state_dict(), bundle.diffusion.model.state_dict()
    assert all(not torch.equal(ema[k], raw[k]) for k in raw)  # every weight of the EMA lags the raw one


def test_ema_follows_the_raw_weights_with_the_declared_decay(
    dataset: WindowDataset, new_bundle, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every ``ema_every`` steps the EMA becomes a copy of the raw weights (before ``ema_start``) or moves
    ``1 - ema_decay`` of the way to them: replaying that recursion on the raw weights seen at those steps gives the
    trained EMA."""
    seen: list[tuple[str, list[torch.Tensor]]] = []

    def spy(kind: str, original):
        def record(dst: torch.nn.Module, src: torch.nn.Module, *args: float) -> None:
            seen.append((kind, [p.detach().clone() for p in src.parameters()]))
            original(dst, src, *args)

        return record

    monkeypatch.setattr(training, "_copy_weights", spy("copy", training._copy_weights))
    monkeypatch.setattr(training, "_update_ema", spy("update", training._update_ema))
    bundle = new_bundle(0)
    cfg = dataclasses.replace(CFG, steps=60, ema_every=5, ema_start=20, ema_decay=0.8)
    replay = [p.detach().clone() for p in bundle.ema.model.parameters()]
    train(bundle, dataset, cfg, CPU, progress=False)
    # steps 5, 10, 15 come before ema_start (copies); 20, 25, ..., 60 are EMA updates
    assert [kind for kind, _ in seen] == ["copy"] * 3 + ["update"] * 9
    for kind, raw in seen:
        replay = raw if kind == "copy" else [0.8 * e + 0.2 * r for e, r in zip(replay, raw, strict=True)]
    for e, r in zip(bundle.ema.model.parameters(), replay, strict=True):
        torch.testing.assert_close(e.detach(), r, rtol=1e-5, atol=1e-6)
    # step 60 is an EMA step: the last raw weights the EMA saw are the trained ones
    for r, p in zip(seen[-1][1], bundle.diffusion.model.parameters(), strict=True):
        assert torch.equal(r, p.detach())


def test_ema_is_a_copy_before_ema_start(dataset: WindowDataset, new_bundle) -> None:
    bundle = new_bundle(0)
    train(bundle, dataset, dataclasses.replace(CFG, steps=10, ema_start=100), CPU, progress=False)
    ema, raw = bundle.ema.model.state_dict(), bundle.diffusion.model.state_dict()
    assert all(torch.equal(ema[k], raw[k]) for k in raw)


def test_resume_file_holds_the_finished_training(tmp_path: Path, dataset: WindowDataset, new_bundle) -> None:
    resume = tmp_path / "resume.pt"
    short = dataclasses.replace(CFG, steps=20)
    first_bundle = new_bundle(0)
    first = train(first_bundle, dataset, short, CPU, resume, "run", progress=False)
    assert [s for s, _ in first] == [5, 10, 15, 20]
    # checkpoints are written at multiples of checkpoint_every and at the end, so that a stage killed after this
    # training (on its next seed) does not train it again
    state = torch.load(resume, weights_only=False)
    assert state["step"] == 20 and state["run_id"] == "run"
    assert state["history"] == first

    # the same training again: nothing is trained, the finished weights and Adam state come back
    again_bundle, logged = new_bundle(7), []
    again = train(
        again_bundle, dataset, short, CPU, resume, "run", on_log=lambda s, _: logged.append(s), progress=False
    )
    assert logged == [] and again == first
    assert_same_weights(weights(again_bundle), weights(first_bundle))
    assert again_bundle.optimizer["adam"]["state"].keys() == first_bundle.optimizer["adam"]["state"].keys()
    for key, moments in first_bundle.optimizer["adam"]["state"].items():
        assert torch.equal(again_bundle.optimizer["adam"]["state"][key]["exp_avg"], moments["exp_avg"])

    # a longer run with the same run_id continues from the end of the shorter one
    second = train(
        new_bundle(7), dataset, CFG, CPU, resume, "run", on_log=lambda s, _: logged.append(s), progress=False
    )
    assert logged == [25, 30]
    assert second[:4] == first
    assert [s for s, _ in second] == [5, 10, 15, 20, 25, 30]
    assert torch.load(resume, weights_only=False)["step"] == 30


def test_killed_and_resumed_training_matches_straight_training(
    tmp_path: Path, dataset: WindowDataset, new_bundle
) -> None:
    straight_bundle = new_bundle(0)
    straight = train(straight_bundle, dataset, CFG, CPU, progress=False)
    assert [s for s, _ in straight] == [5, 10, 15, 20, 25, 30]

    resume = tmp_path / "resume.pt"
    run_id = fingerprint({"cfg": dataclasses.asdict(CFG)})

    def kill_at_25(step: int, loss: float) -> None:
        if step == 25:
            raise Interrupted

    with pytest.raises(Interrupted):
        train(new_bundle(0), dataset, CFG, CPU, resume, run_id, on_log=kill_at_25, progress=False)
    assert torch.load(resume, weights_only=False)["step"] == 20

    # a new process: differently initialised weights, which the resume state must overwrite
    resumed_bundle = new_bundle(123)
    logged: list[int] = []
    resumed = train(
        resumed_bundle, dataset, CFG, CPU, resume, run_id, on_log=lambda s, _: logged.append(s), progress=False
    )
    assert logged == [25, 30]  # it started after step 20
    assert resumed == straight
    assert_same_weights(weights(resumed_bundle), weights(straight_bundle))


def test_resume_state_of_another_run_is_ignored(tmp_path: Path, dataset: WindowDataset, new_bundle) -> None:
    resume = tmp_path / "resume.pt"
    cfg = dataclasses.replace(CFG, steps=20)
    train(new_bundle(5), dataset, cfg, CPU, resume, run_id="old-params", progress=False)
    assert resume.exists()

    logged: list[int] = []
    bundle = new_bundle(0)
    train(bundle, dataset, cfg, CPU, resume, run_id="new-params", on_log=lambda s, _: logged.append(s), progress=False)
    assert logged == [5, 10, 15, 20]  # trained from scratch
    fresh = new_bundle(0)
    train(fresh, dataset, cfg, CPU, progress=False)
    assert_same_weights(weights(bundle), weights(fresh))


def test_a_checkpoint_hook_sees_the_ema_of_each_checkpoint_and_changes_nothing(
    dataset: WindowDataset, new_bundle
) -> None:
    """``on_checkpoint`` runs every ``checkpoint_every`` steps and at the end with the EMA of that step; sampling
    from the EMA there (as a learning curve does) leaves the training run exactly as without the hook."""
    cfg = dataclasses.replace(CFG, steps=25)
    plain = new_bundle(0)
    train(plain, dataset, cfg, CPU, progress=False)
    hooked = new_bundle(0)
    seen: dict[int, dict[str, torch.Tensor]] = {}

    def evaluate(step: int) -> None:
        seen[step] = {k: v.clone() for k, v in hooked.ema.model.state_dict().items()}
        DDIMSampler(2).sample(hooked.ema, {0: torch.zeros(3, 4)}, RowNoise([1, 2, 3]))

    train(hooked, dataset, cfg, CPU, progress=False, on_checkpoint=evaluate)
    assert sorted(seen) == [10, 20, 25]
    assert_same_weights(weights(hooked), weights(plain))
    assert all(torch.equal(seen[25][k], v) for k, v in plain.ema.model.state_dict().items())
    assert any(not torch.equal(seen[10][k], seen[25][k]) for k in seen[25])  # each call saw its own step's EMA


def test_learning_rate_schedules() -> None:
    """Constant without warm-up is exactly lr at every step; warm-up climbs linearly to lr; cosine falls from lr
    to nearly zero at the last step."""
    constant = [training.lr_factor(CFG, s) for s in range(CFG.steps)]
    assert constant == [1.0] * CFG.steps
    warm = dataclasses.replace(CFG, lr_warmup=4)
    assert [training.lr_factor(warm, s) for s in range(6)] == [0.25, 0.5, 0.75, 1.0, 1.0, 1.0]
    cosine = dataclasses.replace(CFG, steps=10, lr_schedule="cosine", lr_warmup=2)
    factors = [training.lr_factor(cosine, s) for s in range(10)]
    assert factors[:3] == [0.5, 1.0, 1.0] and factors[6] == pytest.approx(0.5)
    assert all(a > b for a, b in zip(factors[2:], factors[3:], strict=False)) and 0 < factors[-1] < 0.05


def test_a_killed_cosine_run_resumes_on_its_schedule(tmp_path: Path, dataset: WindowDataset, new_bundle) -> None:
    """The schedule is a function of the step: killed at step 25 and resumed from step 20, the cosine run ends with
    exactly the weights of a straight one, which differ from the constant-rate run's."""
    cfg = dataclasses.replace(CFG, lr_schedule="cosine", lr_warmup=5)
    straight = new_bundle(0)
    train(straight, dataset, cfg, CPU, progress=False)
    constant = new_bundle(0)
    train(constant, dataset, CFG, CPU, progress=False)
    pairs = zip(straight.diffusion.parameters(), constant.diffusion.parameters(), strict=True)
    assert any(not torch.equal(a, b) for a, b in pairs)

    def kill_at_25(step: int, loss: float) -> None:
        if step == 25:
            raise Interrupted

    resume = tmp_path / "resume.pt"
    with pytest.raises(Interrupted):
        train(new_bundle(0), dataset, cfg, CPU, resume, "cosine", on_log=kill_at_25, progress=False)
    resumed = new_bundle(9)
    train(resumed, dataset, cfg, CPU, resume, "cosine", progress=False)
    assert_same_weights(weights(resumed), weights(straight))


@pytest.fixture
def former_sigterm():
    """A Python SIGTERM handler raising :class:`Interrupted`, standing for the process's own (put back afterwards)."""

    def interrupted(signum: int, frame: object) -> None:
        raise Interrupted

    former = signal.signal(signal.SIGTERM, interrupted)
    yield interrupted
    signal.signal(signal.SIGTERM, former)


def sigterm_at(step: int, times: int = 1) -> Callable[[int, float], None]:
    """An ``on_log`` that sends this process SIGTERM ``times`` times when step ``step`` is logged."""

    def on_log(logged: int, loss: float) -> None:
        if logged == step:
            for _ in range(times):
                os.kill(os.getpid(), signal.SIGTERM)

    return on_log


def test_a_stop_signal_waits_for_the_end_of_the_step_and_its_resume_state(
    tmp_path: Path, dataset: WindowDataset, new_bundle, former_sigterm
) -> None:
    """SIGTERM at step 25 (between the checkpoints of 20 and 30): the step ends, its resume state is written, then
    the process's own handler runs; resumed from 25, the run ends with the weights of a straight one."""
    straight = new_bundle(0)
    train(straight, dataset, CFG, CPU, progress=False)

    resume = tmp_path / "resume.pt"
    with pytest.raises(Interrupted):
        train(new_bundle(0), dataset, CFG, CPU, resume, "run", on_log=sigterm_at(25), progress=False)
    assert torch.load(resume, weights_only=False)["step"] == 25  # not 20, the last checkpoint
    assert signal.getsignal(signal.SIGTERM) is former_sigterm  # the process's own handler is back

    logged: list[int] = []
    resumed = new_bundle(7)
    train(resumed, dataset, CFG, CPU, resume, "run", on_log=lambda s, _: logged.append(s), progress=False)
    assert logged == [30]
    assert_same_weights(weights(resumed), weights(straight))


def test_a_second_stop_signal_acts_at_once_and_without_a_resume_state_none_waits(
    tmp_path: Path, dataset: WindowDataset, new_bundle, former_sigterm
) -> None:
    resume = tmp_path / "resume.pt"
    with pytest.raises(Interrupted):
        train(new_bundle(0), dataset, CFG, CPU, resume, "run", on_log=sigterm_at(25, times=2), progress=False)
    assert torch.load(resume, weights_only=False)["step"] == 20  # stopped inside step 25, before its state

    logged: list[int] = []

    def terminate_at_10(step: int, loss: float) -> None:
        logged.append(step)
        if step == 10:
            os.kill(os.getpid(), signal.SIGTERM)
            assert False, "the signal was held without a resume state"  # noqa: B011  (never reached)

    with pytest.raises(Interrupted):
        train(new_bundle(0), dataset, CFG, CPU, on_log=terminate_at_10, progress=False)
    assert logged == [5, 10]


def test_an_error_while_a_stop_signal_waits_ends_training_with_its_own_traceback(
    tmp_path: Path, dataset: WindowDataset, new_bundle, former_sigterm
) -> None:
    def terminate_then_fail_at_15(step: int, loss: float) -> None:
        if step == 15:
            os.kill(os.getpid(), signal.SIGTERM)
            raise ValueError("broken at 15")

    with pytest.raises(ValueError, match="broken at 15"):  # not the signal's Interrupted
        train(new_bundle(0), dataset, CFG, CPU, tmp_path / "resume.pt", "run", on_log=terminate_then_fail_at_15)
    assert signal.getsignal(signal.SIGTERM) is former_sigterm


CHILD = """import sys
from pathlib import Path

import torch

from adaptdiffuser.config import PretrainParams
from adaptdiffuser.training import train

bundle, dataset = torch.load(sys.argv[1], weights_only=False)
cfg = PretrainParams(steps=100_000, batch_size=4, lr=1e-3, log_every=5, checkpoint_every=100_000, seed=3)
train(bundle, dataset, cfg, torch.device("cpu"), Path(sys.argv[2]), "run", progress=False,
      on_log=lambda step, loss: print(f"step {step}", flush=True))
"""


def test_a_training_process_stopped_by_sigterm_ends_by_it_with_its_resume_state_written(
    tmp_path: Path, dataset: WindowDataset, new_bundle
) -> None:
    """A real process (as a stage under `adaptdiffuser run stop`): no checkpoint falls due in its 100 000 steps, yet
    after SIGTERM its resume state holds the step it stopped at, and it ends by the signal, as it would have at once."""
    inputs, resume = tmp_path / "inputs.pt", tmp_path / "resume.pt"
    torch.save((new_bundle(0), dataset), inputs)
    (tmp_path / "child.py").write_text(CHILD)
    env = os.environ | {"OMP_NUM_THREADS": "1"}
    child = subprocess.Popen(
        [sys.executable, str(tmp_path / "child.py"), str(inputs), str(resume)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
    )  # fmt: skip
    assert child.stdout is not None
    watchdog = threading.Timer(300, child.kill)  # a child that never logs step 20 fails the test, not hangs it
    watchdog.start()
    lines = []
    for line in child.stdout:  # training for some steps
        lines.append(line)
        if line.strip() == "step 20":
            break
    child.send_signal(signal.SIGTERM)
    rest, _ = child.communicate(timeout=120)
    watchdog.cancel()
    assert child.returncode == -signal.SIGTERM, "".join(lines) + rest
    stopped = torch.load(resume, weights_only=False)["step"]
    assert 20 <= stopped < 100_000
    assert f"SIGTERM: stopping after step {stopped}, resume state {resume}" in rest


def test_fingerprint() -> None:
    assert fingerprint({"a": 1, "b": [1, 2]}) == fingerprint({"b": [1, 2], "a": 1})
    assert fingerprint({"a": 1}) != fingerprint({"a": 2})
    assert len(fingerprint("x")) == 16
