"""Training loop: Adam, gradient accumulation, EMA, a progress bar, and resumable checkpoints.

The learning rate is ``lr`` throughout (``lr_schedule: constant``, Diffuser's), or follows a cosine from ``lr`` down to
zero at the last step (``cosine``), after ``lr_warmup`` steps of linear warm-up; it is a function of the step alone,
so a resumed run follows it exactly. At the end of training the Adam state of the raw weights is kept in
``bundle.optimizer`` (saved as the bundle's ``optimizer.pt``), so that a fine-tuning run can carry it on
(``evolution.finetune.optimizer: carry``) instead of restarting Adam (``restart``, the default).
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from adaptdiffuser.checkpoint import ModelBundle
from adaptdiffuser.config import PretrainParams
from adaptdiffuser.data.windows import MixedWindowDataset, WindowDataset
from adaptdiffuser.diffusion.conditions import training_conditions
from adaptdiffuser.io import atomic_path
from adaptdiffuser.models.compiled import compile_network
from adaptdiffuser.stop_signals import DeferredStop

LogFn = Callable[[int, float], None]
OPTIMIZER_MODES = ("restart", "carry")


def lr_factor(cfg: PretrainParams, step: int) -> float:
    """The multiple of ``cfg.lr`` used by optimizer step ``step`` (0-based): exactly 1.0 for a constant schedule
    without warm-up."""
    if step < cfg.lr_warmup:
        return (step + 1) / cfg.lr_warmup
    if cfg.lr_schedule == "constant":
        return 1.0
    span = max(cfg.steps - cfg.lr_warmup, 1)
    return 0.5 * (1.0 + math.cos(math.pi * (step - cfg.lr_warmup) / span))


def fingerprint(*parts: Any) -> str:
    """A short hash of JSON-able parts, used to tell whether a resume state belongs to this run."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def load_resume_state(path: Path | None, run_id: str, device: torch.device) -> dict[str, Any] | None:
    """The resume state at ``path`` if there is one written by run ``run_id`` (saying so), else ``None`` (saying
    why, when a state of another run is ignored)."""
    if path is None or not path.exists():
        return None
    state = torch.load(path, map_location=device, weights_only=False)
    if state.get("run_id") != run_id:
        tqdm.write(f"ignoring resume state {path}: it belongs to other params or data")
        return None
    tqdm.write(f"resuming training from step {state['step']} ({path})")
    return state


def loop_state(
    run_id: str,
    step: int,
    optimizer: torch.optim.Optimizer,
    rng: np.random.Generator,
    gen: torch.Generator,
    log: LossLog,
) -> dict[str, Any]:
    """What a training loop needs besides its weights to go on exactly from ``step``: the optimizer, both random
    streams and the loss log (history and the losses since its last mean), with the run it belongs to."""
    return {
        "run_id": run_id,
        "step": step,
        "optimizer": optimizer.state_dict(),
        "numpy_rng": rng.bit_generator.state,
        "torch_rng": gen.get_state(),
        "history": log.history,
        "running": log.running,
    }


def restore_loop_state(
    state: dict[str, Any],
    optimizer: torch.optim.Optimizer,
    rng: np.random.Generator,
    gen: torch.Generator,
    log: LossLog,
) -> int:
    """Put a :func:`loop_state` back into ``optimizer``, ``rng``, ``gen`` and ``log``; return its step."""
    optimizer.load_state_dict(state["optimizer"])
    rng.bit_generator.state = state["numpy_rng"]
    gen.set_state(state["torch_rng"].cpu())
    log.history[:] = state["history"]
    log.running[:] = state.get("running", [])  # states written before it was kept: from a logged step
    return state["step"]


def save_resume_state(path: Path, state: dict[str, Any]) -> None:
    """Write a resume state atomically (a run killed while writing keeps the previous one)."""
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def save_state_when_due(
    resume_path: Path | None, due: bool, stop: DeferredStop, step: int, state: Callable[[int], dict[str, Any]]
) -> None:
    """After step ``step``: write its resume state (``state(step)``) when a checkpoint is ``due`` or a stop signal
    waits, then let a waiting signal take its course (saying so). Nothing without ``resume_path``."""
    if resume_path is None or not (due or stop.received is not None):
        return
    save_resume_state(resume_path, state(step))
    if stop.received is not None:
        tqdm.write(f"{stop.name}: stopping after step {step}, resume state {resume_path}")
        sys.stdout.flush()  # the signal may end the process before Python would
        stop.deliver()


class LossLog:
    """Mean training loss over each ``every`` steps (and at the last step): kept in ``history``, shown on the
    progress bar and passed to ``on_log``."""

    def __init__(self, every: int, last: int, on_log: LogFn | None, bar: tqdm | None = None) -> None:
        self.every, self.last, self.on_log, self.bar = every, last, on_log, bar
        self.history: list[tuple[int, float]] = []
        self.running: list[float] = []

    def add(self, loss: float) -> None:
        self.running.append(loss)

    def step_done(self, done: int) -> None:
        if done % self.every and done != self.last:
            return
        mean_loss = float(np.mean(self.running))
        self.running = []
        self.history.append((done, mean_loss))
        if self.bar is not None:
            self.bar.set_postfix(loss=f"{mean_loss:.4f}")
        if self.on_log:
            self.on_log(done, mean_loss)


def _update_ema(ema: torch.nn.Module, model: torch.nn.Module, decay: float) -> None:
    with torch.no_grad():
        for e, m in zip(ema.parameters(), model.parameters(), strict=True):
            e.lerp_(m, 1.0 - decay)


def _copy_weights(dst: torch.nn.Module, src: torch.nn.Module) -> None:
    dst.load_state_dict(src.state_dict())


def adam_steps(state: dict[str, Any]) -> int:
    """How many updates an Adam ``state_dict`` has made (0 for a fresh one)."""
    steps = [int(s["step"]) for s in state["state"].values() if "step" in s]
    return max(steps, default=0)


def optimizer_record(optimizer: torch.optim.Optimizer) -> dict[str, Any]:
    """What a bundle keeps of its optimizer: a copy of the Adam state and its update count."""
    state = copy.deepcopy(optimizer.state_dict())
    return {"adam": state, "step": adam_steps(state)}


def carried_optimizer(bundle: ModelBundle, mode: str, source: str = "") -> dict[str, Any] | None:
    """The optimizer state a fine-tuning run of ``bundle`` starts from (pass it to ``train``): None with
    ``restart`` (a fresh Adam); the bundle's saved Adam state with ``carry``. A bundle saved before optimizer
    states were kept has none: then Adam restarts, and a message says so."""
    if mode not in OPTIMIZER_MODES:
        raise ValueError(f"optimizer mode must be one of {OPTIMIZER_MODES}, not {mode!r}")
    if mode == "restart":
        return None
    if bundle.optimizer is None:
        tqdm.write(
            f"finetune.optimizer is carry, but the model {source or 'fine-tuning starts from'} has no saved optimizer "
            "state (it was written before optimizer.pt was kept): Adam restarts, as with restart. Retrain that model "
            "to carry its optimizer state."
        )
        return None
    return bundle.optimizer


def train(
    bundle: ModelBundle,
    dataset: WindowDataset | MixedWindowDataset,
    cfg: PretrainParams,
    device: torch.device,
    resume_path: Path | None = None,
    run_id: str = "",
    on_log: LogFn | None = None,
    progress: bool = True,
    optimizer_state: dict[str, Any] | None = None,
    compiled: bool = False,
    on_checkpoint: Callable[[int], None] | None = None,
) -> list[tuple[int, float]]:
    """Train ``bundle`` in place for ``cfg.steps`` steps; resume from ``resume_path`` if it matches ``run_id``.

    The raw weights (``bundle.diffusion``) are trained and the EMA follows them. Adam starts fresh, or from
    ``optimizer_state`` (a ``bundle.optimizer`` record, see ``carried_optimizer``: the moments of these same raw
    weights, with its step count, so the bias correction continues too; this run's ``cfg.lr`` replaces the saved
    learning rate). At the end ``bundle.optimizer`` holds the Adam state. With ``compiled`` the raw network
    runs under ``torch.compile`` (the first step compiles; weights and checkpoints as without). ``on_checkpoint``
    is called with the step count every ``checkpoint_every`` steps and at the end, the EMA up to date, before that
    step's resume state is written (a run killed inside it redoes the step): a learning curve evaluates the EMA
    there (it must not touch the raw weights). The resume state is written at the end too, so that a stage killed
    after this training (on a later seed, say) finds it finished instead of training it again; the caller removes
    it once everything it trains is saved. With ``resume_path``, a SIGTERM or SIGINT waits for the end of the
    step, whose resume state is then written before the signal takes its course (``stop_signals``): a stopped run
    loses no step. Resumed from a finished state, nothing is trained and neither
    ``on_log`` nor ``on_checkpoint`` is called. Returns the
    logged ``(step, loss)`` pairs of the whole run (including those before a resume).
    """
    model, ema = bundle.diffusion.to(device), bundle.ema.to(device)
    model.train()
    if compiled:
        compile_network(model.model, device, "compile.training")
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    if optimizer_state is not None:
        optimizer.load_state_dict(copy.deepcopy(optimizer_state["adam"]))  # never update the caller's record
        for group in optimizer.param_groups:
            group["lr"] = cfg.lr
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator(device=device).manual_seed(cfg.seed)
    start = 0
    state = load_resume_state(resume_path, run_id, device)
    act_dim = model.act_dim
    conditioning = bundle.config.get("conditioning", "start_goal")
    scheduled = cfg.lr_schedule != "constant" or cfg.lr_warmup > 0  # else every step uses cfg.lr as set above
    log = LossLog(cfg.log_every, cfg.steps, on_log)
    if state is not None:
        model.model.load_state_dict(state["model"])
        ema.model.load_state_dict(state["ema"])
        start = restore_loop_state(state, optimizer, rng, gen, log)
    log.bar = bar = tqdm(
        range(start, cfg.steps), initial=start, total=cfg.steps, desc="train", disable=not progress, mininterval=2.0
    )
    with DeferredStop(enabled=resume_path is not None) as stop:
        for step in bar:
            for _ in range(cfg.grad_accum):
                x0 = torch.from_numpy(dataset.sample(cfg.batch_size, rng)).to(device)
                cond = training_conditions(conditioning, x0, act_dim)
                loss = model.loss(x0, cond, generator=gen) / cfg.grad_accum
                loss.backward()
                log.add(loss.item() * cfg.grad_accum)
            if scheduled:
                for group in optimizer.param_groups:
                    group["lr"] = cfg.lr * lr_factor(cfg, step)
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
            done = step + 1
            if done % cfg.ema_every == 0:
                if done < cfg.ema_start:
                    _copy_weights(ema.model, model.model)
                else:
                    _update_ema(ema.model, model.model, cfg.ema_decay)
            log.step_done(done)
            checkpoint = done % cfg.checkpoint_every == 0 or done == cfg.steps
            if on_checkpoint is not None and checkpoint:
                on_checkpoint(done)
            save_state_when_due(
                resume_path, checkpoint, stop, done,
                lambda step: loop_state(run_id, step, optimizer, rng, gen, log)
                | {"model": model.model.state_dict(), "ema": ema.model.state_dict()},
            )  # fmt: skip
    model.eval()
    ema.eval()
    bundle.optimizer = optimizer_record(optimizer)
    return log.history
