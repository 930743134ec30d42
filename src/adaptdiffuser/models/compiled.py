"""The U-Net under ``torch.compile``: the pipeline's fast path (``compile.training`` / ``compile.sampling`` in params).

Compiling changes how the network runs, not what it computes: inductor fuses each GroupNorm with the Mish after it
(see :class:`~adaptdiffuser.models.unet.Mish`), and outputs equal the eager network's within float rounding. The
first call of each input shape compiles (tens of seconds on a CPU, a few seconds from inductor's on-disk cache);
batch sizes that change afterwards are compiled once more with a symbolic batch size."""

from __future__ import annotations

import os
import shutil

import torch
from torch import nn

from adaptdiffuser.config.errors import ConfigError

CPP_COMPILERS = ("g++", "c++", "clang++")


def compile_network(network: nn.Module, device: torch.device, setting: str) -> None:
    """Compile ``network`` in place (``nn.Module.compile``: its weights, state dict and checkpoints unchanged). On a
    CPU inductor builds C++ kernels, so a missing compiler is reported here, naming ``setting``, the params key that
    asked for it."""
    if device.type == "cpu" and not (os.environ.get("CXX") or any(shutil.which(c) for c in CPP_COMPILERS)):
        raise ConfigError(
            f"{setting}: true needs a C++ compiler for torch.compile on the CPU, and none was found "
            f"({', '.join(CPP_COMPILERS)} or $CXX); install one (Debian: g++) or set {setting}: false"
        )
    network.compile()
