#!/usr/bin/env bash
# Create .venv (if needed) and install adaptdiffuser with its dev tools, at the versions of requirements.lock
# (scripts/lock.sh makes it; nothing is resolved here). Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
# --no-compile: Python compiles each module when it is first imported instead of pip compiling every file of every
# package up front (install 61 s instead of 147 s on the AVX2-only 2-core EPYC, docs/speed.md).
PIP=(.venv/bin/pip install --quiet --no-compile)
# torch is pinned to the CPU build (a looser range pulls several GB of CUDA packages).
"${PIP[@]}" "torch==2.13.0"
lock_python="$(sed -n 's/.*for Python \([0-9.]*\) on.*/\1/p' requirements.lock | head -1)"
venv_python="$(.venv/bin/python -c 'import sys; print(*sys.version_info[:2], sep=".")')"
if [ "$lock_python" = "$venv_python" ]; then
  "${PIP[@]}" --no-deps -r requirements.lock
  .venv/bin/python scripts/check_lock.py   # the lock still matches pyproject.toml
  "${PIP[@]}" --no-deps -e .
  .venv/bin/pip check >/dev/null || { .venv/bin/pip check; exit 1; }
else
  echo "warning: requirements.lock is for Python $lock_python and this is $venv_python: resolving pyproject.toml" >&2
  "${PIP[@]}" -e ".[dev]"
fi
