#!/usr/bin/env bash
# Maze2D Large's phase-0 validation curve, to choose science-large's pretraining steps (docs/maze2d.md): the
# profile's expert data and reference, then benchmarks/recipe_study.py on benchmarks/recipes/maze2d-large.yaml,
# training seed 0, scored every 2 000 steps on 30 validation episodes (seed 7, never the evaluation seed). Points go to
# metrics/curves/maze2d-large/ as they are measured. Rerunning it after any stop continues: DVC skips the data, the
# curve resumes from its last state. Long (5-9 h of one thread by CPU: 0.43-0.78 CPU-s a step measured on AVX2-only
# EPYCs): run it in the background,
#   adaptdiffuser profile science-large && OMP_NUM_THREADS=1 adaptdiffuser run start -- bash scripts/large_curve.sh
set -euo pipefail
cd "$(dirname "$0")/.."
dvc repro reference@maze2d-large
python benchmarks/recipe_study.py . --task maze2d-large --recipes benchmarks/recipes/maze2d-large.yaml \
  --training-seeds 0 --every 2000 --episodes 30 --out-dir metrics/curves/maze2d-large
