"""Training the value network of Diffuser's locomotion guidance, and its checkpoint folder.

The value network learns ``V(x_t, t)``: the return-to-go of a window's first step, from the window noised to a
uniformly drawn diffusion step ``t`` with the diffusion model's own forward process (``q_sample``) and with its
first state inpainted, exactly as the sampler presents noisy plans during guided planning.

A value checkpoint folder holds ``value.pt`` (weights) and ``config.json`` (the network's constructor arguments
under ``"network"``, the settings and any extra info). It has no normalizer: the diffusion bundle's is used.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from adaptdiffuser.config.value_settings import ValueSettings
from adaptdiffuser.data.returns import ValueWindowDataset
from adaptdiffuser.diffusion.conditions import apply_inpainting
from adaptdiffuser.diffusion.gaussian import GaussianDiffusion
from adaptdiffuser.io import atomic_dir, read_json, write_json
from adaptdiffuser.models.value_network import ValueNetwork
from adaptdiffuser.stop_signals import DeferredStop
from adaptdiffuser.training import (
    LogFn,
    LossLog,
    load_resume_state,
    loop_state,
    restore_loop_state,
    save_state_when_due,
)

VALUE_FILES = ("value.pt", "config.json")


def value_loss(
    value_net: torch.nn.Module,
    diffusion: GaussianDiffusion,
    x0: torch.Tensor,
    target: torch.Tensor,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Mean squared error of the value of noisy, first-state-inpainted windows ``x0`` against ``target``."""
    t, xt = noised_windows(diffusion, x0, generator)
    return ((value_net(xt, t) - target) ** 2).mean()


def noised_windows(
    diffusion: GaussianDiffusion, x0: torch.Tensor, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniformly drawn diffusion steps and ``x0`` noised to them with its first state inpainted, as the sampler
    presents noisy plans to the value during guidance."""
    t = torch.randint(0, diffusion.n_steps, (x0.shape[0],), device=x0.device, generator=generator)
    noise = torch.randn(x0.shape, device=x0.device, generator=generator)
    act_dim = diffusion.act_dim
    return t, apply_inpainting(diffusion.q_sample(x0, t, noise), {0: x0[:, 0, act_dim:]}, act_dim)


def train_value(
    value_net: torch.nn.Module,
    diffusion: GaussianDiffusion,
    dataset: ValueWindowDataset,
    settings: ValueSettings,
    device: torch.device,
    progress: bool = True,
    on_log: LogFn | None = None,
    resume_path: Path | None = None,
    run_id: str = "",
) -> list[tuple[int, float]]:
    """Train ``value_net`` in place (Adam) for ``settings.steps`` steps; return the logged ``(step, mean loss)``
    of the whole run.

    ``diffusion`` supplies only the noise schedule (it is moved to ``device``, not trained). Seeded by
    ``settings.seed`` (window draws, steps and noise); the network's initial weights are the caller's. With
    ``resume_path``, a resume state is written every ``settings.checkpoint_every`` steps and at the end, and a
    state of the same ``run_id`` found there is gone on from (a finished one: nothing trained, nothing logged),
    exactly as the diffusion model's :func:`~adaptdiffuser.training.train`; the caller removes it.
    """
    value_net.to(device).train()
    diffusion.to(device)
    optimizer = torch.optim.Adam(value_net.parameters(), lr=settings.lr)
    rng = np.random.default_rng(settings.seed)
    gen = torch.Generator(device=device).manual_seed(settings.seed)
    start = 0
    log = LossLog(settings.log_every, settings.steps, on_log)
    state = load_resume_state(resume_path, run_id, device)
    if state is not None:
        value_net.load_state_dict(state["model"])
        start = restore_loop_state(state, optimizer, rng, gen, log)
    log.bar = bar = tqdm(
        range(start, settings.steps), initial=start, total=settings.steps, desc="value", disable=not progress,
        mininterval=2.0,
    )  # fmt: skip
    with DeferredStop(enabled=resume_path is not None) as stop:
        for step in bar:
            windows, values = dataset.sample(settings.batch_size, rng)
            x0 = torch.from_numpy(windows).to(device)
            target = torch.from_numpy(values).to(device)
            loss = value_loss(value_net, diffusion, x0, target, generator=gen)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            log.add(loss.item())
            done = step + 1
            log.step_done(done)
            save_state_when_due(
                resume_path, done % settings.checkpoint_every == 0 or done == settings.steps, stop, done,
                lambda step: loop_state(run_id, step, optimizer, rng, gen, log) | {"model": value_net.state_dict()},
            )  # fmt: skip
    value_net.eval()
    return log.history


@torch.no_grad()
def heldout_r2(
    value_net: torch.nn.Module,
    diffusion: GaussianDiffusion,
    dataset: ValueWindowDataset,
    windows: int,
    seed: int,
    device: torch.device,
    batch_size: int = 256,
) -> dict[str, float]:
    """The coefficient of determination ``1 - SSE / SST`` of the value on ``windows`` windows drawn from
    ``dataset`` (episodes it was not trained on): ``r2`` at noise levels drawn as in training, ``r2_t0`` on clean
    windows (the plan the guidance ends on). Seeded by ``seed``."""
    value_net.to(device).eval()
    diffusion.to(device)
    x0, target = (torch.from_numpy(a).to(device) for a in dataset.sample(windows, np.random.default_rng(seed)))
    gen = torch.Generator(device=device).manual_seed(seed)
    noisy, clean = [], []
    for i in range(0, windows, batch_size):
        xb = x0[i : i + batch_size]
        t, xt = noised_windows(diffusion, xb, gen)
        noisy.append(value_net(xt, t))
        clean.append(value_net(xb, torch.zeros_like(t)))

    def r2(predicted: torch.Tensor) -> float:
        total = ((target - target.mean()) ** 2).sum()
        return float(1.0 - ((predicted - target) ** 2).sum() / total) if total > 0 else float("nan")

    return {"r2": r2(torch.cat(noisy)), "r2_t0": r2(torch.cat(clean)), "windows": windows}


def save_value(path: str | Path, value_net: ValueNetwork, info: dict[str, Any] | None = None) -> None:
    """Write a value checkpoint folder (``value.pt``, ``config.json``) atomically; ``info`` goes into the config
    (e.g. ``{"settings": settings.model_dump()}``)."""
    with atomic_dir(path) as tmp:
        torch.save(value_net.state_dict(), tmp / "value.pt")
        write_json(tmp / "config.json", {"network": value_net.config(), **(info or {})})


def load_value(path: str | Path, device: str | torch.device = "cpu") -> tuple[ValueNetwork, dict[str, Any]]:
    """Load a value checkpoint folder: the network (in eval mode, on ``device``) and its config; raise
    ``FileNotFoundError`` naming the missing folder or file."""
    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"value checkpoint folder not found: {path} (run the stage that trains it)")
    for name in VALUE_FILES:
        if not (path / name).exists():
            raise FileNotFoundError(f"value checkpoint {path} is incomplete: no {name} (run the stage that trains it)")
    config = read_json(path / "config.json", "value config")
    net = ValueNetwork(**config["network"])
    net.load_state_dict(torch.load(path / "value.pt", map_location="cpu", weights_only=True))
    return net.to(device).eval(), config
