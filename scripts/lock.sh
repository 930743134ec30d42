#!/usr/bin/env bash
# Re-resolve requirements.lock from pyproject.toml: a fresh virtual environment gets the project with its dev tools,
# and every installed version is written down. Run after changing a dependency; commit the lock with it.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-python3}"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$PYTHON" -m venv "$tmp/venv"
"$tmp/venv/bin/pip" install --quiet "torch==2.13.0"
"$tmp/venv/bin/pip" install --quiet ".[dev]"
{
  echo "# The exact versions scripts/setup.sh installs (with --no-deps), for Python $("$tmp/venv/bin/python" -c 'import sys; print(*sys.version_info[:2], sep=".")') on $(uname -m) Linux."
  echo "# Made by scripts/lock.sh from pyproject.toml; torch (the CPU build, 2.13.0) is installed on its own."
  "$tmp/venv/bin/pip" freeze --exclude-editable | grep -v -E "^(torch|adaptdiffuser)[=@ ]"
} > requirements.lock.tmp
mv requirements.lock.tmp requirements.lock
echo "requirements.lock: $(grep -c "==" requirements.lock) packages"
