"""Per-seed results of a stage that evaluates every training seed in turn, kept outside its outputs until the stage
has written them all: a stage killed on training seed s takes the seeds before it from their records when it runs
again, instead of playing their episodes again (DVC removes a stage's outputs before it reruns it, so the records
live among the resume states, ignored by git and DVC)."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from tqdm import tqdm

from adaptdiffuser.io import atomic_dir, atomic_path, read_json, write_json
from adaptdiffuser.stages.common import source_digest
from adaptdiffuser.training import fingerprint

RECORD = "record.json"


def _copy(source: Path, target: Path) -> None:
    """Copy a file or folder to ``target`` as a whole (atomically)."""
    if source.is_dir():
        with atomic_dir(target) as tmp:
            shutil.copytree(source, tmp, dirs_exist_ok=True)
    else:
        with atomic_path(target) as tmp:
            shutil.copy2(source, tmp)


def recorded_metrics(root: Path, record: Path, key: str, outputs: list[Path]) -> dict | None:
    """The metrics that ``record`` (a folder relative to ``root``) holds for a run whose settings and inputs hash to
    ``key``, after putting its copies of that run's ``outputs`` back at their paths; ``None`` when there is no such
    record (a record of other settings or inputs is ignored, saying so)."""
    meta = root / record / RECORD
    if not meta.is_file():
        return None
    saved = read_json(meta)
    if saved.get("key") != key:
        tqdm.write(f"ignoring {record}: it was written for other settings, inputs or code")
        return None
    for i, out in enumerate(outputs):
        copy = root / record / f"output{i}"
        if copy.exists():
            _copy(copy, root / out)
    tqdm.write(f"{record}: evaluated before this stage was interrupted; its results are taken up again")
    return saved["metrics"]


def write_record(root: Path, record: Path, key: str, metrics: dict, outputs: list[Path]) -> None:
    """Keep ``metrics`` and copies of ``outputs`` (relative to ``root``; those that exist) in ``record``, atomically."""
    with atomic_dir(root / record) as tmp:
        for i, out in enumerate(outputs):
            if (root / out).exists():
                _copy(root / out, tmp / f"output{i}")
        write_json(tmp / RECORD, {"key": key, "metrics": metrics})


def each_seed(
    root: Path,
    seeds: Iterable[int],
    record: Callable[[int], Path],
    key: Callable[[int], str],
    outputs: Callable[[int], list[Path]],
    run: Callable[[int], dict],
) -> dict[int, dict]:
    """``run(seed)`` for every seed, each seed's metrics and ``outputs(seed)`` recorded in ``record(seed)`` as soon as
    it is done, or taken from a record of the same ``key(seed)`` that an interrupted earlier run left; the caller
    removes the records (:func:`remove_records`) once it has written the stage's own outputs over seeds."""
    per_seed = {}
    for seed in seeds:
        seed_key = key(seed)
        kept = recorded_metrics(root, record(seed), seed_key, outputs(seed))
        if kept is None:
            kept = run(seed)
            write_record(root, record(seed), seed_key, kept, outputs(seed))
        per_seed[seed] = kept
    return per_seed


def remove_records(root: Path, records: Iterable[Path]) -> None:
    """Remove records that are no longer needed (the stage's outputs over seeds are written)."""
    for record in records:
        shutil.rmtree(root / record, ignore_errors=True)


def evaluation_key(*parts: Any, model: Path | None = None, files: Iterable[Path] = ()) -> str:
    """The key of one seed's evaluation: its settings (``parts``, JSON-able), its model folder's contents and the
    digests of any other input files that exist."""
    digests = [source_digest(path) if path.exists() else None for path in [model, *files] if path is not None]
    return fingerprint(parts, digests)
