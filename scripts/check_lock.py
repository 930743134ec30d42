"""Check that requirements.lock satisfies pyproject.toml: every dependency (and the dev extra's) is pinned there at
a version its specifier allows. Exit 1 naming the first mismatches and the command that relocks."""

from __future__ import annotations

import sys
from pathlib import Path

import tomllib
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
SEPARATELY = {"torch"}  # installed on its own by scripts/setup.sh (the CPU build)


def main() -> int:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    wanted = [Requirement(r) for r in [*project["dependencies"], *project["optional-dependencies"]["dev"]]]
    pinned = {}
    for line in (ROOT / "requirements.lock").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, version = line.split("==")
            pinned[canonicalize_name(name)] = version.strip()
    problems = []
    for req in wanted:
        name = canonicalize_name(req.name)
        if name in SEPARATELY:
            continue
        if name not in pinned:
            problems.append(f"{req.name} is not in requirements.lock")
        elif not req.specifier.contains(pinned[name], prereleases=True):
            problems.append(f"{req.name}=={pinned[name]} does not satisfy {req}")
    if problems:
        print(f"requirements.lock does not match pyproject.toml: {'; '.join(problems)} (run scripts/lock.sh)")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
