"""Training loop: Adam, gradient accumulation, EMA, a progress bar, and resumable checkpoints."""

from __future__ import annotations

import hashlib
import json
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

LogFn = Callable[[int, float], None]


def fingerprint(*parts: Any) -> str:
    """A short hash of JSON-able parts, used to tell whether a resume state belongs to this run."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


class LossLog:
    """Mean training loss over each ``every`` steps (and at the last step): kept in ``history``, shown on the
    progress bar and passed to ``on_log``."""

    def __init__(self, every: int, last: int, bar: tqdm, on_log: LogFn | None, history: list | None = None) -> None:
        self.every, self.last, self.bar, self.on_log = every, last, bar, on_log
        self.history: list[tuple[int, float]] = history if history is not None else []
        self.running: list[float] = []

    def add(self, loss: float) -> None:
        self.running.append(loss)

    def step_done(self, done: int) -> None:
        if done % self.every and done != self.last:
            return
        mean_loss = float(np.mean(self.running))
        self.running = []
        self.history.append((done, mean_loss))
        self.bar.set_postfix(loss=f"{mean_loss:.4f}")
        if self.on_log:
            self.on_log(done, mean_loss)


def _update_ema(ema: torch.nn.Module, model: torch.nn.Module, decay: float) -> None:
    with torch.no_grad():
        for e, m in zip(ema.parameters(), model.parameters(), strict=True):
            e.lerp_(m, 1.0 - decay)


def _copy_weights(dst: torch.nn.Module, src: torch.nn.Module) -> None:
    dst.load_state_dict(src.state_dict())


def train(
    bundle: ModelBundle,
    dataset: WindowDataset | MixedWindowDataset,
    cfg: PretrainParams,
    device: torch.device,
    resume_path: Path | None = None,
    run_id: str = "",
    on_log: LogFn | None = None,
    progress: bool = True,
) -> list[tuple[int, float]]:
    """Train ``bundle`` in place for ``cfg.steps`` steps; resume from ``resume_path`` if it matches ``run_id``.

    Returns the logged ``(step, loss)`` pairs of the whole run (including those before a resume).
    """
    model, ema = bundle.diffusion.to(device), bundle.ema.to(device)
    model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator(device=device).manual_seed(cfg.seed)
    start, history = 0, []
    if resume_path is not None and resume_path.exists():
        state = torch.load(resume_path, map_location=device, weights_only=False)
        if state.get("run_id") == run_id:
            model.model.load_state_dict(state["model"])
            ema.model.load_state_dict(state["ema"])
            optimizer.load_state_dict(state["optimizer"])
            rng.bit_generator.state = state["numpy_rng"]
            gen.set_state(state["torch_rng"].cpu())
            start, history = state["step"], state["history"]
            tqdm.write(f"resuming training from step {start} ({resume_path})")
        else:
            tqdm.write(f"ignoring resume state {resume_path}: it belongs to other params or data")
    act_dim = model.act_dim
    conditioning = bundle.config.get("conditioning", "start_goal")
    bar = tqdm(
        range(start, cfg.steps), initial=start, total=cfg.steps, desc="train", disable=not progress, mininterval=2.0
    )
    log = LossLog(cfg.log_every, cfg.steps, bar, on_log, history)
    for step in bar:
        for _ in range(cfg.grad_accum):
            x0 = torch.from_numpy(dataset.sample(cfg.batch_size, rng)).to(device)
            cond = training_conditions(conditioning, x0, act_dim)
            loss = model.loss(x0, cond, generator=gen) / cfg.grad_accum
            loss.backward()
            log.add(loss.item() * cfg.grad_accum)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        done = step + 1
        if done % cfg.ema_every == 0:
            if done < cfg.ema_start:
                _copy_weights(ema.model, model.model)
            else:
                _update_ema(ema.model, model.model, cfg.ema_decay)
        log.step_done(done)
        if resume_path is not None and done % cfg.checkpoint_every == 0 and done < cfg.steps:
            state = {
                "run_id": run_id,
                "step": done,
                "model": model.model.state_dict(),
                "ema": ema.model.state_dict(),
                "optimizer": optimizer.state_dict(),
                "numpy_rng": rng.bit_generator.state,
                "torch_rng": gen.get_state(),
                "history": history,
            }
            with atomic_path(resume_path) as tmp:
                torch.save(state, tmp)
    model.eval()
    ema.eval()
    return history
