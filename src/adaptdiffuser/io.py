"""Atomic file output: write to a temporary sibling, then rename, so a killed stage never leaves half a file.

Temporary files and folders are created with the modes ``open()`` and ``mkdir()`` use (0o666 and 0o777, less the
umask, applied by the system), not ``mkstemp``'s 0o600, so a shared DVC cache or another user can read the outputs.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

_ATTEMPTS = 100


def _create_sibling(path: Path, create: Callable[[Path], None]) -> Path:
    """Create a new ``.<name>.<random>.tmp`` beside ``path`` with ``create`` (which fails if it exists)."""
    for _ in range(_ATTEMPTS):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
        try:
            create(tmp)
        except FileExistsError:
            continue
        return tmp
    raise FileExistsError(f"no free temporary name beside {path} after {_ATTEMPTS} tries")


def _create_file(tmp: Path) -> None:
    """An empty file with the mode ``open(tmp, "w")`` would give (0o666 less the umask)."""
    os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path``, on error it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp_path = _create_sibling(path, _create_file)
    mode = tmp_path.stat().st_mode & 0o7777
    try:
        yield tmp_path
        if tmp_path.stat().st_mode & 0o7777 != mode:  # a writer that replaced the file (e.g. via its own mkstemp)
            os.chmod(tmp_path, mode)
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


@contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield a temporary directory beside ``path``; on success it replaces ``path`` as a whole."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _create_sibling(path, lambda p: p.mkdir(0o777))  # 0o777 less the umask, as a plain mkdir
    try:
        yield tmp
        if path.exists():
            old = path.with_name(f".{path.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def write_json(path: str | Path, data: Any) -> None:
    """Write ``data`` as indented JSON, atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")


def read_json(path: str | Path, what: str = "file") -> Any:
    """Read a JSON file, with an error that names ``what`` is missing."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what} not found: {path}")
    return json.loads(path.read_text())
