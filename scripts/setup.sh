#!/usr/bin/env bash
# Create .venv (if needed) and install adaptdiffuser at the versions of requirements.lock; with --dev also its dev
# tools (tests, linters) from requirements-dev.lock. scripts/lock.sh makes both; nothing is resolved here. Safe to run
# again.
set -euo pipefail
cd "$(dirname "$0")/.."
dev=false
case "$*" in
  --dev) dev=true ;;
  "") ;;
  *) echo "usage: bash scripts/setup.sh [--dev]" >&2; exit 2 ;;
esac
PYTHON="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
# Packages are byte-compiled once below on every core rather than file by file by pip (--no-compile): with the dev
# tools left out, the install takes 105-117 s instead of 146 s on the AVX2-only 2-core EPYC (docs/speed.md).
PIP=(.venv/bin/pip install --quiet --no-compile)
# torch is pinned to the CPU build (a looser range pulls several GB of CUDA packages).
"${PIP[@]}" "torch==2.13.0"
lock_python="$(sed -n 's/.*for Python \([0-9.]*\) on.*/\1/p' requirements.lock | head -1)"
venv_python="$(.venv/bin/python -c 'import sys; print(*sys.version_info[:2], sep=".")')"
if [ "$lock_python" = "$venv_python" ]; then
  locks=(-r requirements.lock)
  if $dev; then locks+=(-r requirements-dev.lock); fi
  "${PIP[@]}" --no-deps "${locks[@]}"
  .venv/bin/python scripts/check_lock.py   # the locks still match pyproject.toml
  "${PIP[@]}" --no-deps -e .
  .venv/bin/pip check >/dev/null || { .venv/bin/pip check; exit 1; }
else
  echo "warning: requirements.lock is for Python $lock_python and this is $venv_python: resolving pyproject.toml" >&2
  if $dev; then "${PIP[@]}" -e ".[dev]"; else "${PIP[@]}" -e .; fi
fi
# Compile what pip left uncompiled. A module that does not compile is left to its import, as pip leaves it; should
# compileall fail altogether, every module compiles on import instead: slower stages, the same results.
site_packages="$(.venv/bin/python -c 'import sysconfig; print(sysconfig.get_path("purelib"))')"
.venv/bin/python -m compileall -q -j 0 "$site_packages" >/dev/null 2>&1 || true
