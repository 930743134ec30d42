"""The code a task's stages run: the generic core plus the folder of the task's family, and a fingerprint of it.

DVC cannot pick a deps folder by a task's family inside one templated stage, so one stage per task (``code@<task>``,
deps: :func:`code_paths` of its family) writes ``code/<task>.json``, the digest of every file of those paths, and the
task's other stages depend on that file. Editing one family's code changes only its tasks' fingerprints; every other
task's stages stay up to date.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from adaptdiffuser.config.errors import ConfigError

PACKAGE_DIR = Path(__file__).resolve().parent.parent
SOURCE_PREFIX = Path("src/adaptdiffuser")  # where the package lives in the project (dvc.yaml names it so)
FAMILIES_DIR = "families"
#: files of ``families/`` that belong to the core: the package marker
FAMILIES_CORE = ("__init__.py",)
SKIPPED = ("__pycache__",)


def fingerprint_path(task: str) -> Path:
    """Where the ``code`` stage writes the fingerprint of ``task``'s code."""
    return Path("code") / f"{task}.json"


def core_paths(package_dir: Path = PACKAGE_DIR) -> list[str]:
    """The generic core, as ``dvc.yaml`` lists it: every entry of the package except the families' folders."""
    entries = sorted(p.name for p in package_dir.iterdir() if p.name not in SKIPPED and p.name != FAMILIES_DIR)
    core = [(SOURCE_PREFIX / name).as_posix() for name in entries]
    return core + [(SOURCE_PREFIX / FAMILIES_DIR / name).as_posix() for name in FAMILIES_CORE]


def code_paths(family: str, package_dir: Path = PACKAGE_DIR) -> list[str]:
    """What a task of ``family`` runs: the core and ``families/<family>`` (paths relative to the project)."""
    if not (package_dir / FAMILIES_DIR / family).is_dir():
        known = sorted(p.name for p in (package_dir / FAMILIES_DIR).iterdir() if p.is_dir() and p.name not in SKIPPED)
        raise ConfigError(f"family {family!r}: no folder {FAMILIES_DIR}/{family} in {package_dir} (families: {known})")
    return [*core_paths(package_dir), (SOURCE_PREFIX / FAMILIES_DIR / family).as_posix()]


def _files(path: Path) -> list[Path]:
    if path.is_file():
        return [path]
    return sorted(p for p in path.rglob("*") if p.is_file() and not any(part in SKIPPED for part in p.parts))


def fingerprint(root: Path, family: str) -> dict[str, Any]:
    """The family and the MD5 of every file the task's code consists of, keyed by path relative to ``root``."""
    digests: dict[str, str] = {}
    for entry in code_paths(family, root / SOURCE_PREFIX):
        for file in _files(root / entry):
            digests[file.relative_to(root).as_posix()] = hashlib.md5(file.read_bytes()).hexdigest()
    return {"family": family, "files": dict(sorted(digests.items()))}
