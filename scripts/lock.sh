#!/usr/bin/env bash
# Re-resolve the locks from pyproject.toml: a fresh virtual environment gets the project with its dev tools and every
# installed version is written down, split in one resolution into requirements.lock (what the pipeline needs: the
# project's own dependencies) and requirements-dev.lock (what only the dev extra adds). Run after changing a
# dependency; commit both locks with it.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-python3}"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$PYTHON" -m venv "$tmp/venv"
pip=("$tmp/venv/bin/pip" install --quiet --no-compile)
"${pip[@]}" "torch==2.13.0"
"${pip[@]}" ".[dev]"
"$tmp/venv/bin/pip" freeze --exclude-editable | grep -v -E "^(torch|adaptdiffuser)[=@ ]" > "$tmp/all.txt"
# which of them the project alone needs: pip's resolution of "." constrained to the versions just installed
{ cat "$tmp/all.txt"; echo "torch==2.13.0"; } > "$tmp/constraints.txt"
"${pip[@]}" --dry-run --ignore-installed --report "$tmp/runtime.json" -c "$tmp/constraints.txt" .
python_version="$("$tmp/venv/bin/python" -c 'import sys; print(*sys.version_info[:2], sep=".")')"
"$tmp/venv/bin/python" - "$tmp" "$python_version" "$(uname -m)" <<'PY'
import json
import sys

from packaging.utils import canonicalize_name as canon

tmp, python_version, machine = sys.argv[1:]
runtime = {canon(item["metadata"]["name"]) for item in json.load(open(f"{tmp}/runtime.json"))["install"]}
lines = [line for line in open(f"{tmp}/all.txt").read().splitlines() if line.strip()]
unpinned = [line for line in lines if "==" not in line]
if unpinned:
    sys.exit(f"lock.sh: not a pinned release, cannot be locked: {unpinned}")
run = [line for line in lines if canon(line.split("==")[0]) in runtime]
dev = [line for line in lines if canon(line.split("==")[0]) not in runtime]
with open(f"{tmp}/requirements.lock", "w") as out:
    out.write(
        "# The exact versions scripts/setup.sh installs (with --no-deps) to run the pipeline, for Python "
        f"{python_version} on {machine} Linux.\n# Made by scripts/lock.sh from pyproject.toml; torch (the CPU build, "
        "2.13.0) is installed on its own, the dev tools\n# (scripts/setup.sh --dev, for the tests) from "
        "requirements-dev.lock.\n" + "\n".join(run) + "\n"
    )
with open(f"{tmp}/requirements-dev.lock", "w") as out:
    out.write(
        "# The dev tools' exact versions (pyproject's dev extra), installed by scripts/setup.sh --dev on top of\n"
        "# requirements.lock; made by scripts/lock.sh in the same resolution.\n" + "\n".join(dev) + "\n"
    )
print(f"requirements.lock: {len(run)} packages; requirements-dev.lock: {len(dev)}")
PY
for lock in requirements.lock requirements-dev.lock; do   # each replaced whole (a rename within the folder)
  cp "$tmp/$lock" ".$lock.tmp" && mv ".$lock.tmp" "$lock"
done
