"""Record a code change that leaves every output as it is: refresh ``code/<task>.json`` for the tasks in
``dvc.lock`` and put the new digests in the entries that depend on them, without rerunning any stage.

For a change that cannot alter what a stage writes (a resume state, a docstring, a new option off by default, a
refactor shown byte for byte): DVC would otherwise rerun every stage of every task. Do not use it for anything else;
``dvc repro`` is the way to record a change in outputs. Run from the repository root, then check in a workspace
holding the pipeline's outputs that ``dvc status`` says "Data and pipelines are up to date".

    python scripts/relock_code.py
"""

from __future__ import annotations

import hashlib
import subprocess
from pathlib import Path

import yaml

LOCK = Path("dvc.lock")


def code_stages(lock: dict) -> list[str]:
    """The ``code@<task>`` stages ``dvc.lock`` holds."""
    return [name for name in lock["stages"] if name.startswith("code@")]


def swap(text: str, old: str, new: str) -> str:
    """``text`` with ``old`` replaced by ``new`` wherever it occurs."""
    return text.replace(old, new) if old != new else text


def digest_lines(dep: dict) -> str:
    """How ``dvc.lock`` writes a dep's digest: md5, size and, for a folder, its file count."""
    lines = f"md5: {dep['md5']}\n      size: {dep['size']}"
    return lines + (f"\n      nfiles: {dep['nfiles']}" if "nfiles" in dep else "")


def main() -> None:
    text = LOCK.read_text()
    lock = yaml.safe_load(text)
    for stage in code_stages(lock):
        out = Path(lock["stages"][stage]["outs"][0]["path"])
        before = lock["stages"][stage]["outs"][0]["md5"]
        subprocess.run(["dvc", "repro", "--single-item", stage], check=True, capture_output=True)
        text = LOCK.read_text()
        after = yaml.safe_load(text)["stages"][stage]["outs"][0]["md5"]
        text = swap(text, before, after)  # the stages that depend on the task's code digest
        print(f"{stage}: {out} {before} -> {after}")
    lock = yaml.safe_load(text)
    fresh = {dep["path"]: dep for stage in code_stages(lock) for dep in lock["stages"][stage]["deps"]}
    for name, entry in lock["stages"].items():  # stages that list source paths themselves (summarize, report)
        for dep in entry.get("deps", []):
            now = fresh.get(dep["path"]) or source_file_digest(dep["path"])
            if now is not None and now["md5"] != dep["md5"]:
                text = swap(text, digest_lines(dep), digest_lines(now))
                print(f"{name}: {dep['path']}")
    LOCK.write_text(text)


def source_file_digest(path: str) -> dict | None:
    """A source file's digest as ``dvc.lock`` records it (md5 of its bytes, size), for a file of ``src/`` or
    ``pipeline/`` inside a folder the code stages list whole; None for anything else (data are never relocked)."""
    file = Path(path)
    if not file.is_file() or file.parts[0] not in ("src", "pipeline"):
        return None
    data = file.read_bytes()
    return {"md5": hashlib.md5(data).hexdigest(), "size": len(data)}


if __name__ == "__main__":
    main()
