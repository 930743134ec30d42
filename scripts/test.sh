#!/usr/bin/env bash
# README command 2 (and CI): set up, lint, and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --dev
# shellcheck disable=SC1091
source .venv/bin/activate
ruff check src pipeline tests benchmarks
lint-imports   # the import contracts of pyproject.toml (docs/architecture.md)
# One worker per core (pytest-xdist); a file's tests stay on one worker (tests/conftest.py groups them). Pass
# `-n 0` to run in this process, e.g. `bash scripts/test.sh -n 0 tests/test_io.py`.
pytest -q -n logical --dist loadgroup "$@"
