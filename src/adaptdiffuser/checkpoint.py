"""Model bundles on disk: weights, EMA weights, normalizer and the config they were trained with.

A bundle directory (``models/phase0/``) holds ``model.pt``, ``ema.pt``, ``normalizer.json`` and
``config.json``, and, for a trained bundle, ``optimizer.pt`` (the Adam state of the raw weights at the end of
training, which fine-tuning may carry on with); it is written as a whole, atomically. Bundles written before
``optimizer.pt`` existed still load, with ``optimizer`` None.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch

from adaptdiffuser.config import DiffusionParams, ModelParams
from adaptdiffuser.data.normalizer import Normalizer
from adaptdiffuser.diffusion.gaussian import GaussianDiffusion
from adaptdiffuser.io import atomic_dir, read_json, write_json
from adaptdiffuser.models.unet import TemporalUnet

BUNDLE_FILES = ("model.pt", "ema.pt", "normalizer.json", "config.json")
OPTIMIZER_FILE = "optimizer.pt"  # optional: absent from untrained bundles and from those saved before it existed


def build_diffusion(model: ModelParams, diffusion: DiffusionParams, obs_dim: int, act_dim: int) -> GaussianDiffusion:
    """A fresh diffusion model (U-Net denoiser inside) from params."""
    net = TemporalUnet(
        obs_dim + act_dim, dim=model.dim, dim_mults=tuple(model.dim_mults), kernel_size=model.kernel_size
    )
    return GaussianDiffusion(
        net,
        horizon=diffusion.horizon,
        obs_dim=obs_dim,
        act_dim=act_dim,
        n_steps=diffusion.n_steps,
        predict_epsilon=diffusion.predict_epsilon,
        clip_denoised=diffusion.clip_denoised,
        action_weight=diffusion.action_weight,
        loss_discount=diffusion.loss_discount,
    )


@dataclass
class ModelBundle:
    """A trained model: the raw and EMA diffusion models, the normalizer and the training config.

    ``optimizer`` is the Adam state of the raw weights (``diffusion``) after the last training step, as
    ``{"adam": optimizer.state_dict(), "step": Adam updates so far}``; None before training, or when loaded from
    a bundle saved without it.
    """

    diffusion: GaussianDiffusion
    ema: GaussianDiffusion
    normalizer: Normalizer
    config: dict[str, Any]
    optimizer: dict[str, Any] | None = None


def make_bundle(
    model: ModelParams,
    diffusion: DiffusionParams,
    obs_dim: int,
    act_dim: int,
    normalizer: Normalizer,
    **info: Any,
) -> ModelBundle:
    """A new, untrained bundle; ``info`` is stored in its config (task, data, phase...)."""
    diff = build_diffusion(model, diffusion, obs_dim, act_dim)
    config = {
        "model": asdict(model),
        "diffusion": asdict(diffusion),
        "obs_dim": obs_dim,
        "act_dim": act_dim,
        **info,
    }
    return ModelBundle(diff, copy.deepcopy(diff), normalizer, config)


def save_bundle(path: str | Path, bundle: ModelBundle) -> None:
    """Write the bundle directory atomically (a reader never sees half of it)."""
    with atomic_dir(path) as tmp:
        torch.save(bundle.diffusion.model.state_dict(), tmp / "model.pt")
        torch.save(bundle.ema.model.state_dict(), tmp / "ema.pt")
        write_json(tmp / "normalizer.json", bundle.normalizer.state_dict())
        write_json(tmp / "config.json", bundle.config)
        if bundle.optimizer is not None:
            torch.save(bundle.optimizer, tmp / OPTIMIZER_FILE)


def load_bundle(path: str | Path, device: str | torch.device = "cpu", ema_only: bool = False) -> ModelBundle:
    """Load a bundle; raise ``FileNotFoundError`` naming the missing checkpoint file (``optimizer.pt`` is optional).

    With ``ema_only``, load a kept model (:mod:`adaptdiffuser.stages.kept_models`): its EMA weights serve as both
    models and ``model.pt`` may be absent."""
    path = Path(path)
    needed = [name for name in BUNDLE_FILES if not (ema_only and name == "model.pt")]
    hint = "a kept model lists its files in metrics/kept-models.json" if ema_only else "run the stage that trains it"
    for name in needed:
        if not (path / name).exists():
            raise FileNotFoundError(f"checkpoint {path} is incomplete or missing: no {name} ({hint})")
    config = read_json(path / "config.json")
    model = ModelParams(**config["model"])
    diffusion = DiffusionParams(**config["diffusion"])
    normalizer = Normalizer.from_state_dict(read_json(path / "normalizer.json"))
    bundle = make_bundle(model, diffusion, config["obs_dim"], config["act_dim"], normalizer)
    bundle.config = config
    ema = torch.load(path / "ema.pt", map_location="cpu", weights_only=True)
    raw = ema if ema_only else torch.load(path / "model.pt", map_location="cpu", weights_only=True)
    bundle.diffusion.model.load_state_dict(raw)
    bundle.ema.model.load_state_dict(ema)
    if (path / OPTIMIZER_FILE).exists():
        bundle.optimizer = torch.load(path / OPTIMIZER_FILE, map_location="cpu", weights_only=True)
    bundle.diffusion.to(device)
    bundle.ema.to(device)
    return bundle
