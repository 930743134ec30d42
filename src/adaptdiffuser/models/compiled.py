"""The U-Net under ``torch.compile``: the pipeline's fast path (``compile.training`` / ``compile.sampling`` in params).

Compiling changes how the network runs, not what it computes: inductor fuses each GroupNorm with the Mish after it
(see :class:`~adaptdiffuser.models.unet.Mish`), and outputs equal the eager network's within float rounding. The
first call of each input shape compiles (tens of seconds on a CPU, a few seconds from inductor's on-disk cache);
batch sizes that change afterwards are compiled once more with a symbolic batch size.

Inductor's on-disk cache is the project's own, per user (:func:`inductor_cache_dir`), and a process killed while
compiling cannot poison it: a shared object it left unfinished would otherwise be loaded by every later compiled
run (``ImportError: ... file too short``); :func:`remove_unfinished_libraries` deletes such files before compiling,
so inductor builds them again."""

from __future__ import annotations

import logging
import os
import shutil
import struct
from pathlib import Path

import torch
from torch import nn

from adaptdiffuser.config.errors import ConfigError

CPP_COMPILERS = ("g++", "c++", "clang++")
CACHE_ENV = "TORCHINDUCTOR_CACHE_DIR"
log = logging.getLogger(__name__)


def inductor_cache_dir() -> Path:
    """Where inductor keeps compiled kernels: ``$TORCHINDUCTOR_CACHE_DIR`` when set, else the project's own folder
    per user and torch version (``$XDG_CACHE_HOME`` or ``~/.cache``, then ``adaptdiffuser/inductor-<torch>``), which
    is then set for this process (inductor reads the variable)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    folder = base / "adaptdiffuser" / f"inductor-{torch.__version__}"
    os.environ[CACHE_ENV] = str(folder)
    return folder


def is_unfinished_library(path: Path) -> bool:
    """Whether the shared object ``path`` is cut short: no ELF header, or shorter than its header says (the
    program and section header tables must lie inside the file)."""
    with open(path, "rb") as f:
        head = f.read(64)
        size = os.fstat(f.fileno()).st_size
    if len(head) < 52 or head[:4] != b"\x7fELF" or head[4] not in (1, 2) or head[5] not in (1, 2):
        return True
    order = "<" if head[5] == 1 else ">"
    if head[4] == 2:  # 64-bit
        if len(head) < 64:
            return True
        phoff, shoff = struct.unpack_from(order + "QQ", head, 0x20)
        phentsize, phnum, shentsize, shnum = struct.unpack_from(order + "HHHH", head, 0x36)
    else:
        phoff, shoff = struct.unpack_from(order + "II", head, 0x1C)
        phentsize, phnum, shentsize, shnum = struct.unpack_from(order + "HHHH", head, 0x2A)
    return phoff + phentsize * phnum > size or shoff + shentsize * shnum > size


def remove_unfinished_libraries(cache: Path) -> list[Path]:
    """Delete the shared objects under ``cache`` that a killed compile left unfinished; return them."""
    removed = []
    for path in sorted(cache.rglob("*.so")) if cache.is_dir() else []:
        try:
            if is_unfinished_library(path):
                path.unlink()
                removed.append(path)
        except OSError:  # another process replaced or removed it meanwhile
            continue
    if removed:
        log.warning("removed %d unfinished compiled kernels from %s (a compile was interrupted)", len(removed), cache)
    return removed


def compile_network(network: nn.Module, device: torch.device, setting: str) -> None:
    """Compile ``network`` in place (``nn.Module.compile``: its weights, state dict and checkpoints unchanged). On a
    CPU inductor builds C++ kernels, so a missing compiler is reported here, naming ``setting``, the params key that
    asked for it. Unfinished kernels in the cache are removed first (:func:`remove_unfinished_libraries`)."""
    if device.type == "cpu" and not (os.environ.get("CXX") or any(shutil.which(c) for c in CPP_COMPILERS)):
        raise ConfigError(
            f"{setting}: true needs a C++ compiler for torch.compile on the CPU, and none was found "
            f"({', '.join(CPP_COMPILERS)} or $CXX); install one (Debian: g++) or set {setting}: false"
        )
    remove_unfinished_libraries(inductor_cache_dir())
    network.compile()
