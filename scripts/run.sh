#!/usr/bin/env bash
# README command 1: set up a fresh machine and run the default (quick) pipeline end to end.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# shellcheck disable=SC1091
source .venv/bin/activate
dvc repro
adaptdiffuser times   # how long each stage took (its MLflow runs)
dvc metrics show
