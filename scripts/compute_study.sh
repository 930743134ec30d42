#!/usr/bin/env bash
# The gain of evolution against phase-0 training (docs/maze2d.md, "Gain against phase-0 training"): the pipeline of
# params.yaml run once per pretraining length given, each length's record kept in metrics/science/<task>-compute/
# steps-<n>/ (its summary, params and per-seed task metrics), then the curve over every recorded length written to
# metrics/science/<task>-compute.json and docs/science/<task>-compute.png (scripts/compute_curve.py).
#   adaptdiffuser profile science-umaze-compute && bash scripts/compute_study.sh 1250 2500 5000 10000 20000
# STEPS_KEY names the params key that holds the length (default pretrain.steps; a task whose entry states its own
# recipe, such as Medium: STEPS_KEY=task.maze2d-medium.pretrain.steps). Rerunning it after any stop, on this machine
# or on another after a commit, continues: a length whose record is whole and whose params equal this run's is not
# run again, DVC restores or skips trained models and resumes training from its checkpoint. params.yaml is left as the
# profile wrote it. Long (about 4 h on 2 cores for five lengths up to 20 000 steps): run it in the background,
#   adaptdiffuser run start -- bash scripts/compute_study.sh 1250 2500 5000 10000 20000
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -gt 0 ] || { echo "usage: bash scripts/compute_study.sh STEPS [STEPS ...]" >&2; exit 2; }
for n in "$@"; do
  [[ "$n" =~ ^[1-9][0-9]*$ ]] || { echo "compute_study: a length must be a positive whole number of steps, got '$n'" >&2; exit 2; }
done
key=${STEPS_KEY:-pretrain.steps}
task=$(python -c 'import yaml; print(yaml.safe_load(open("params.yaml"))["evolve"])')
tasks=$(python -c 'import yaml; print(" ".join(yaml.safe_load(open("params.yaml"))["tasks"]))')
profile_value=$(KEY=$key python -c '
import os, yaml
value = yaml.safe_load(open("params.yaml"))
for part in os.environ["KEY"].split("."):
    value = value[part]
print(value)')
trap 'adaptdiffuser set "$key=$profile_value" > /dev/null' EXIT   # params.yaml as the profile wrote it
study=metrics/science/$task-compute
mkdir -p "$study"
for n in "$@"; do
  record=$study/steps-$n
  adaptdiffuser set "$key=$n" > /dev/null
  if [ -f "$record/summary.json" ] && cmp -s "$record/params.yaml" params.yaml; then
    echo "== $task, $key=$n: recorded ($record), not run again"
    continue
  fi
  echo "== $(date -u +%FT%TZ) $task: $key=$n"
  rm -rf "$record"
  dvc repro
  # the record, whole or absent: built beside it, then renamed into place
  rm -rf "$record.tmp" && mkdir "$record.tmp"
  for ran in $tasks; do cp -r "metrics/tasks/$ran" "$record.tmp/"; done
  cp params.yaml "$record.tmp/params.yaml"
  cp metrics/summary.json "$record.tmp/summary.json"
  mv "$record.tmp" "$record"
  python scripts/compute_curve.py "$study" --key "$key"   # the curve so far: commit it with the record
done
