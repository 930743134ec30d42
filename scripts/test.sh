#!/usr/bin/env bash
# README command 2 (and CI): set up, lint, and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --dev
# shellcheck disable=SC1091
source .venv/bin/activate
ruff check src pipeline tests benchmarks
lint-imports   # the import contracts of pyproject.toml (docs/architecture.md)
# One pytest-xdist worker per core, each test sent to whichever is free, except that tests sharing a costly fixture go
# to one worker together (tests/conftest.py marks their groups), so it is built once. Pass `-n 0` to run in this
# process: `bash scripts/test.sh -n 0 tests/test_io.py`.
pytest -q -n logical --dist loadgroup "$@"
