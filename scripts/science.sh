#!/usr/bin/env bash
# The science profile in one command: U-Maze and Hopper-medium, three training seeds, phases 0..2 with their
# equal-compute controls. DVC runs one evolved task at a time, so the pipeline runs twice: once evolving
# maze2d-umaze, once evolving hopper-medium (phase 0 of both tasks is computed once and cached). Each run's summary
# is kept under metrics/science/<task>.json and the gains of both are printed at the end.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck disable=SC1091
source .venv/bin/activate
adaptdiffuser profile science
mkdir -p metrics/science
# `evolution` is one section for whichever task evolves: U-Maze uses the science profile's, Hopper the
# quick-locomotion profile's (value-guided DDPM plans from dataset states and resets, the paper's thresholds).
adaptdiffuser set evolve=maze2d-umaze
dvc repro
cp metrics/summary.json metrics/science/maze2d-umaze.json
adaptdiffuser set evolve=hopper-medium
adaptdiffuser set evolution.generate.tasks=1024
adaptdiffuser set evolution.generate.sampler=ddpm
adaptdiffuser set evolution.generate.sampler_steps=20
dvc repro
cp metrics/summary.json metrics/science/hopper-medium.json
adaptdiffuser gains metrics/science/maze2d-umaze.json metrics/science/hopper-medium.json
