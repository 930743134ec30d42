#!/usr/bin/env bash
# README command 2 (and CI): set up, lint, and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --dev
# shellcheck disable=SC1091
source .venv/bin/activate
ruff check src pipeline tests benchmarks
lint-imports   # the import contracts of pyproject.toml (docs/architecture.md)
pytest -q "$@"
