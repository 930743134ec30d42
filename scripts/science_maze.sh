#!/usr/bin/env bash
# Both Maze2D evolution recipes on the profile in params.yaml (science-medium, science-large, or any profile that
# evolves a Maze2D task), one after the other in this folder: `plans`, then the author's `rollouts`. The recipe is
# a generic key (evolution.generate.recipe), so the second pass reruns the phases only: phase 0 and phase 1's
# equal-compute control are the first pass's (phase k's control starts from phase k-1: that recipe's). Each pass's
# summary goes to metrics/science/<task>.json (plans) and metrics/science/<task>-rollouts.json, its per-seed task
# metrics (metrics/tasks/) to metrics/science/<task>/ and <task>-rollouts/; params.yaml is left
# as the profile wrote it, and the params each pass ran with to metrics/science/<name>.params.yaml. Rerunning the
# script after any stop continues where it stopped: a pass this run has finished (its summary there, differing from
# the commit's, beside its per-seed folder and a params record equal to params.yaml as the pass would run) is not run
# again (remove its summary to rerun it), DVC skips or restores (run cache) the trained models, training resumes from
# its checkpoint, and the uncached stages (discrimination, evaluations: minutes) rerun. So a run restored on another
# machine in its second pass needs the first pass's record carried (summary, per-seed folder, params), not its
# models. Arguments name the passes to run, in order (default: plans rollouts); `rollouts` alone trains its own
# control. Long: run it in the background (docs/operations.md, long runs),
#   adaptdiffuser profile science-medium && adaptdiffuser run start -- bash scripts/science_maze.sh
set -euo pipefail
cd "$(dirname "$0")/.."
known=$(python -c 'from adaptdiffuser.families.maze2d.params import RECIPES; print(" ".join(RECIPES))')
recipes=${*:-$known}
for recipe in $recipes; do
  [[ " $known " == *" $recipe "* ]] || { echo "science_maze.sh: unknown recipe '$recipe' (${known// / or })" >&2; exit 2; }
done
task=$(python -c 'import yaml; print(yaml.safe_load(open("params.yaml"))["evolve"])')
tasks=$(python -c 'import yaml; print(" ".join(yaml.safe_load(open("params.yaml"))["tasks"]))')
trap 'adaptdiffuser set evolution.generate.recipe=plans > /dev/null' EXIT   # params.yaml as the profile wrote it
mkdir -p metrics/science
copy_whole() {  # copy file $1 to $2 so that $2 is whole or absent
  cp "$1" "$2.tmp" && mv "$2.tmp" "$2"
}
done_here() {  # pass $1 finished in this run with these params: its record whole, its summary not the commit's
  local record=metrics/science/$1
  [ -f "$record.json" ] && [ -d "$record" ] && [ -f "$record.params.yaml" ] &&
    cmp -s "$record.params.yaml" params.yaml &&
    [ "$(git rev-parse -q --verify "HEAD:$record.json" || true)" != "$(git hash-object "$record.json")" ]
}
for recipe in $recipes; do
  name=$task
  [ "$recipe" = plans ] || name=$task-$recipe
  adaptdiffuser set "evolution.generate.recipe=$recipe" > /dev/null
  if done_here "$name"; then
    echo "== $task: the $recipe pass is done (metrics/science/$name.json, this run's): not run again"
    continue
  fi
  echo "== $(date -u +%FT%TZ) $task: evolution.generate.recipe=$recipe"
  rm -f "metrics/science/$name.json"   # an earlier summary (other params) marks nothing done while the pass reruns
  dvc repro
  # the pass's record, its summary last (what marks the pass done): its per-seed metrics of the tasks it ran (the next
  # pass rewrites metrics/tasks/; what pools seeds run apart, adaptdiffuser pool), its params, its summary
  rm -rf "metrics/science/$name.tmp" && mkdir "metrics/science/$name.tmp"
  for ran in $tasks; do cp -r "metrics/tasks/$ran" "metrics/science/$name.tmp/"; done
  rm -rf "metrics/science/$name" && mv "metrics/science/$name.tmp" "metrics/science/$name"
  copy_whole params.yaml "metrics/science/$name.params.yaml"
  copy_whole metrics/summary.json "metrics/science/$name.json"
done
[ "$recipes" != "$known" ] || adaptdiffuser gains "metrics/science/$task.json" "metrics/science/$task-rollouts.json"
