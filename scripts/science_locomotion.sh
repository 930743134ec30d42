#!/usr/bin/env bash
# The science-locomotion profile's evolved tasks, one after the other in this folder: Walker2d-medium, then
# Hopper-medium (`evolve` names one task per DVC run; phase 0 of every task, HalfCheetah's included, is computed in
# the first run and cached). Each run's summary goes to metrics/science/<evolved task>.json, and the last one also to
# metrics/science/halfcheetah-medium.json (its phase 0); params.yaml is left as the profile wrote it. Rerunning the
# script after any stop continues where it stopped (DVC skips or restores what is done; training resumes from its
# checkpoint). Long: run it in the background (docs/operations.md, long runs),
#   adaptdiffuser profile science-locomotion && adaptdiffuser run start -- bash scripts/science_locomotion.sh
set -euo pipefail
cd "$(dirname "$0")/.."
first=$(python -c 'import yaml; print(yaml.safe_load(open("params.yaml"))["evolve"])')
trap 'adaptdiffuser set "evolve=$first" > /dev/null' EXIT   # params.yaml as the profile wrote it
mkdir -p metrics/science
save() {   # whole or absent
  cp metrics/summary.json "$1.tmp"
  mv "$1.tmp" "$1"
}
for task in walker2d-medium hopper-medium; do
  echo "== $(date -u +%FT%TZ) evolve=$task"
  adaptdiffuser set "evolve=$task"
  dvc repro
  save "metrics/science/$task.json"
done
save metrics/science/halfcheetah-medium.json
adaptdiffuser gains metrics/science/walker2d-medium.json metrics/science/hopper-medium.json
