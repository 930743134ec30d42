"""Check that the locks satisfy pyproject.toml: every dependency is pinned in requirements.lock, every dev-extra one
in requirements.lock or requirements-dev.lock, at a version its specifier allows, and no package is in both; and,
once installed, that what requirements.lock's packages require is in requirements.lock too (the pipeline's install
leaves requirements-dev.lock out). Exit 1 naming the first mismatches and the command that relocks."""

from __future__ import annotations

import sys
from importlib import metadata
from pathlib import Path

import tomllib
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
SEPARATELY = {"torch"}  # installed on its own by scripts/setup.sh (the CPU build)
WITH_PYTHON = {"pip", "setuptools"}  # in every virtual environment, never locked (pip freeze leaves them out)


def read_lock(path: Path) -> dict[str, str]:
    """Package name (canonical) -> pinned version."""
    pinned = {}
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, version = line.split("==")
            pinned[canonicalize_name(name)] = version.strip()
    return pinned


def mismatches(wanted: list[Requirement], pinned: dict[str, str], lock_name: str) -> list[str]:
    problems = []
    for req in wanted:
        name = canonicalize_name(req.name)
        if name in SEPARATELY:
            continue
        if name not in pinned:
            problems.append(f"{req.name} is not in {lock_name}")
        elif not req.specifier.contains(pinned[name], prereleases=True):
            problems.append(f"{req.name}=={pinned[name]} does not satisfy {req}")
    return problems


def outside_runtime(runtime: dict[str, str]) -> list[str]:
    """Requirements of the installed runtime-lock packages that the runtime lock lacks (none installed: none)."""
    problems = []
    for name in sorted(runtime):
        try:
            requires = metadata.requires(name) or []
        except metadata.PackageNotFoundError:
            continue
        for text in requires:
            req = Requirement(text)
            if req.marker is not None and not req.marker.evaluate({"extra": ""}):
                continue  # an extra's requirement or another platform's
            needed = canonicalize_name(req.name)
            if needed not in runtime and needed not in SEPARATELY | WITH_PYTHON:
                problems.append(f"{name} requires {req.name}, which requirements.lock lacks")
    return problems


def main() -> int:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    runtime = read_lock(ROOT / "requirements.lock")
    dev = read_lock(ROOT / "requirements-dev.lock")
    problems = mismatches([Requirement(r) for r in project["dependencies"]], runtime, "requirements.lock")
    dev_wanted = [Requirement(r) for r in project["optional-dependencies"]["dev"]]
    problems += mismatches(dev_wanted, runtime | dev, "requirements.lock or requirements-dev.lock")
    problems += [f"{name} is in both locks" for name in sorted(runtime.keys() & dev.keys())]
    problems += outside_runtime(runtime)
    if problems:
        print(f"the locks do not match pyproject.toml: {'; '.join(problems)} (run scripts/lock.sh)")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
