#!/usr/bin/env bash
# Both Maze2D evolution recipes on the profile in params.yaml (science-medium, science-large, or any profile that
# evolves a Maze2D task), one after the other in this folder: `plans`, then the author's `rollouts`. The recipe is
# a generic key (evolution.generate.recipe), so the second pass reruns the phases only: phase 0 and phase 1's
# equal-compute control are the first pass's (phase k's control starts from phase k-1: that recipe's). Each pass's
# summary goes to metrics/science/<task>.json (plans) and metrics/science/<task>-rollouts.json, its per-seed task
# metrics (metrics/tasks/) to metrics/science/<task>/ and <task>-rollouts/; params.yaml is left
# as the profile wrote it. Rerunning the script after any stop continues where it stopped: DVC skips or restores
# (run cache) the trained models of both recipes, training resumes from its checkpoint, and the uncached stages
# (discrimination, evaluations: minutes) rerun. Long: run it in a pinned clone,
#   bash scripts/long_run.sh start ../runs/science-medium --profile science-medium --script scripts/science_maze.sh
set -euo pipefail
cd "$(dirname "$0")/.."
task=$(python -c 'import yaml; print(yaml.safe_load(open("params.yaml"))["evolve"])')
tasks=$(python -c 'import yaml; print(" ".join(yaml.safe_load(open("params.yaml"))["tasks"]))')
trap 'adaptdiffuser set evolution.generate.recipe=plans > /dev/null' EXIT   # params.yaml as the profile wrote it
mkdir -p metrics/science
for recipe in plans rollouts; do
  echo "== $(date -u +%FT%TZ) $task: evolution.generate.recipe=$recipe"
  adaptdiffuser set "evolution.generate.recipe=$recipe"
  dvc repro
  name=$task
  [ "$recipe" = plans ] || name=$task-$recipe
  cp metrics/summary.json "metrics/science/$name.json.tmp"
  mv "metrics/science/$name.json.tmp" "metrics/science/$name.json"   # whole or absent
  # the pass's per-seed metrics of the tasks it ran beside its summary (the next pass rewrites metrics/tasks/): what
  # pools seeds run apart (adaptdiffuser pool)
  rm -rf "metrics/science/$name.tmp" && mkdir "metrics/science/$name.tmp"
  for ran in $tasks; do cp -r "metrics/tasks/$ran" "metrics/science/$name.tmp/"; done
  rm -rf "metrics/science/$name" && mv "metrics/science/$name.tmp" "metrics/science/$name"
done
adaptdiffuser gains "metrics/science/$task.json" "metrics/science/$task-rollouts.json"
