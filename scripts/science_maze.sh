#!/usr/bin/env bash
# Both Maze2D evolution recipes on the profile in params.yaml (science-medium, science-large, or any profile that
# evolves a Maze2D task), one after the other in this folder: `plans`, then the author's `rollouts`. The recipe is
# a generic key (evolution.generate.recipe), so the second pass reruns the phases only: phase 0 and phase 1's
# equal-compute control are the first pass's (phase k's control starts from phase k-1: that recipe's). Each pass's
# summary goes to metrics/science/<task>.json (plans) and metrics/science/<task>-rollouts.json, its per-seed task
# metrics (metrics/tasks/) to metrics/science/<task>/ and <task>-rollouts/; params.yaml is left
# as the profile wrote it. Rerunning the script after any stop continues where it stopped: a pass whose summary this
# run has written (one that differs from the commit's) is not run again (remove the summary to rerun it), DVC skips
# or restores (run cache) the trained models, training resumes from its checkpoint, and the uncached stages
# (discrimination, evaluations: minutes) rerun. So a run restored on another machine in its second pass
# (long_run.sh start --restore) needs the first pass's summary and per-seed folder carried, not its models.
# Long: run it in a pinned clone,
#   bash scripts/long_run.sh start ../runs/science-medium --profile science-medium --script scripts/science_maze.sh
set -euo pipefail
cd "$(dirname "$0")/.."
task=$(python -c 'import yaml; print(yaml.safe_load(open("params.yaml"))["evolve"])')
tasks=$(python -c 'import yaml; print(" ".join(yaml.safe_load(open("params.yaml"))["tasks"]))')
trap 'adaptdiffuser set evolution.generate.recipe=plans > /dev/null' EXIT   # params.yaml as the profile wrote it
mkdir -p metrics/science
written_here() {  # pass $1's summary and per-seed folder are there, the summary not as the commit has it
  [ -f "metrics/science/$1.json" ] && [ -d "metrics/science/$1" ] &&
    [ -n "$(git status --porcelain -- "metrics/science/$1.json")" ]
}
for recipe in plans rollouts; do
  name=$task
  [ "$recipe" = plans ] || name=$task-$recipe
  if written_here "$name"; then
    echo "== $task: the $recipe pass is done (metrics/science/$name.json, this run's): not run again"
    continue
  fi
  echo "== $(date -u +%FT%TZ) $task: evolution.generate.recipe=$recipe"
  adaptdiffuser set "evolution.generate.recipe=$recipe"
  dvc repro
  cp metrics/summary.json "metrics/science/$name.json.tmp"
  mv "metrics/science/$name.json.tmp" "metrics/science/$name.json"   # whole or absent
  # the pass's per-seed metrics of the tasks it ran beside its summary (the next pass rewrites metrics/tasks/): what
  # pools seeds run apart (adaptdiffuser pool)
  rm -rf "metrics/science/$name.tmp" && mkdir "metrics/science/$name.tmp"
  for ran in $tasks; do cp -r "metrics/tasks/$ran" "metrics/science/$name.tmp/"; done
  rm -rf "metrics/science/$name" && mv "metrics/science/$name.tmp" "metrics/science/$name"
done
adaptdiffuser gains "metrics/science/$task.json" "metrics/science/$task-rollouts.json"
