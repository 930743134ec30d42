#!/usr/bin/env bash
# Long runs (the science profiles: hours to days on 2 CPU cores) in their own clone pinned to a commit, so that work
# on this repository cannot make them stale; the same one command continues a run after any interruption.
#
#   bash scripts/long_run.sh start FOLDER [--profile NAME] [--set KEY=VALUE ...] [--script FILE] [--commit REV]
#                                         [--from REPO] [--venv VENV] [--foreground] [--after OTHER] [--restore SAVE]
#       clone REPO (default: this repository) at REV (default: its HEAD) into FOLDER, install it there (or use VENV's
#       packages with FOLDER/src first on PYTHONPATH), switch to profile NAME (default: the commit's params.yaml),
#       set each KEY=VALUE in its params.yaml (`adaptdiffuser set`; --set repeats) and start `dvc repro` in the
#       background (log: FOLDER/long_run.log), or FILE, a bash script of the clone that runs `dvc repro` itself and
#       reruns cleanly (scripts/science_maze.sh: both Maze2D recipes); with --after OTHER (a long run's folder), not
#       now but once OTHER's run has finished, so the CPU goes from one run to the next; not at all if OTHER is
#       stopped or fails first (`resume` then starts it); with --restore SAVE (a `save --carry` of a run of the same
#       commit, profile and settings, perhaps on a machine that is gone), from what that run had carried: its
#       training resume states and finished stages' outputs with its dvc.lock, so only what it had left runs
#   bash scripts/long_run.sh resume FOLDER [--foreground] [--after OTHER]
#       continue where it stopped: DVC skips the stages that finished, training resumes from its last checkpoint
#       (models/.resume/), an evaluation from its last finished training seed, the other stages rerun from their
#       start (minutes at most); --after OTHER as for start
#   bash scripts/long_run.sh status FOLDER
#       the pinned commit, whether it runs, the stages left, the resume states and the log's last lines
#   bash scripts/long_run.sh stop FOLDER
#       stop the run and everything it started (to free the CPU for other work); `resume` continues it, training
#       from its last checkpoint
#   bash scripts/long_run.sh save FOLDER [--into DIR] [--carry PATH ...]
#       copy what the run has measured so far (its metrics/ files that differ from the pinned commit's, params.yaml,
#       dvc.lock, the commit) into DIR (default: metrics/runs/<FOLDER's name>; replaced whole if it holds this run's
#       last save, refused if another run's), to commit before a session ends: its measurements outlive the machine;
#       --carry PATH (a file or folder of the run, e.g. models/.resume or models/TASK/phase0; repeats) copies it
#       into DIR/carry/ too, so `start --restore DIR` continues the run on another machine (committed with the save:
#       megabytes each, so carry the hours of training only)
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"

usage() { sed -n '4,31p' "$0" >&2; exit 2; }
die() { echo "long_run: $*" >&2; exit 2; }

[ $# -ge 2 ] || usage
action=$1
folder=$(realpath -m "$2")
shift 2
profile="" script="" commit="HEAD" source="$here" venv="" foreground=0 into="" after="" restore="" settings=() carry=()
while [ $# -gt 0 ]; do
  case $1 in
    --profile) profile=$2; shift 2 ;;
    --set) settings+=("$2"); shift 2 ;;
    --script) script=$2; shift 2 ;;
    --commit) commit=$2; shift 2 ;;
    --from) source=$2; shift 2 ;;
    --venv) venv=$(realpath "$2"); shift 2 ;;
    --foreground) foreground=1; shift ;;
    --into) into=$(realpath -m "$2"); shift 2 ;;
    --after) after=$(realpath -m "$2"); shift 2 ;;
    --carry) carry+=("$2"); shift 2 ;;
    --restore) restore=$(realpath -m "$2"); shift 2 ;;
    *) die "unknown option $1" ;;
  esac
done
[ -z "$restore" ] || [ "$action" = start ] || die "--restore is for start (a new clone; a failed restore: remove FOLDER, start again)"
[ ${#carry[@]} = 0 ] || [ "$action" = save ] || die "--carry is for save"

group_alive() {  # whether a process of group $1 is alive (a zombie not yet reaped is not)
  local stat line fields
  for stat in /proc/[0-9]*/stat; do
    { read -r line < "$stat"; } 2>/dev/null || continue   # the process ended while we looked
    read -r -a fields <<< "${line##*) }"             # after "pid (comm) ": state, ppid, pgrp, ...
    [ "${fields[2]}" = "$1" ] && [ "${fields[0]}" != Z ] && return 0
  done
  return 1
}

running_pid() {  # the pid of the run in FOLDER (or in folder $1) if it is alive (a zombie not yet reaped is not)
  local run=${1:-$folder} pid state
  [ -f "$run/long_run.pid" ] || return 1
  pid=$(cat "$run/long_run.pid")
  kill -0 "$pid" 2>/dev/null || return 1
  state=$(sed 's/.*) //' "/proc/$pid/stat" 2>/dev/null | cut -d' ' -f1)
  [ "$state" != Z ] && echo "$pid"
}

environment() {  # the run's tools: the clone's own .venv, or VENV's with the clone's sources first
  # shellcheck disable=SC1091
  source "$folder/.long_run.env"
  if [ -n "$LONG_RUN_VENV" ]; then
    export PATH="$LONG_RUN_VENV/bin:$PATH" PYTHONPATH="$folder/src${PYTHONPATH:+:$PYTHONPATH}"
  else
    export PATH="$folder/.venv/bin:$PATH"
  fi
  export DVC_NO_ANALYTICS=1
  unset MLFLOW_TRACKING_URI
}

launch() {  # its exit status goes to long_run.rc when it ends by itself (none when it is stopped or killed)
  if pid=$(running_pid) && [ "$pid" != $$ ]; then die "$folder is already running (pid $pid)"; fi
  environment
  cd "$folder"
  rm -f long_run.rc long_run.after   # a waiter's note: this run is not waiting any more
  local run=(dvc repro) rc=0
  if [ -n "${LONG_RUN_SCRIPT:-}" ]; then run=(bash "$LONG_RUN_SCRIPT"); fi
  echo "== $(date -u +%FT%TZ) ${run[*]} at $(git rev-parse --short HEAD)" >> long_run.log
  if [ "$foreground" = 1 ]; then
    echo $$ > long_run.pid
    "${run[@]}" >> long_run.log 2>&1 || rc=$?
    echo "$rc" > long_run.rc
    [ "$rc" = 0 ] || die "${run[*]} failed: see $folder/long_run.log"
  else
    setsid nohup bash -c '"$@"; echo $? > long_run.rc' long_run "${run[@]}" >> long_run.log 2>&1 < /dev/null &
    echo $! > long_run.pid
    echo "running in the background (pid $!): bash scripts/long_run.sh status $folder"
  fi
}

finished() {  # whether the long run in folder $1 ended by itself with exit status 0
  [ "$(cat "$1/long_run.rc" 2>/dev/null)" = 0 ] && ! running_pid "$1" > /dev/null
}

check_after() {  # --after names another long run that runs or has finished (before anything is cloned)
  [ -f "$after/.long_run.env" ] || die "--after $after is not a long run"
  [ "$after" != "$folder" ] || die "--after $after is this run"
  finished "$after" || running_pid "$after" > /dev/null ||
    die "--after $after neither runs nor has finished (resume it, or run $folder without --after)"
}

check_restore() {  # --restore names a save of a run of this commit, profile and settings that carried something
  local record="$restore/run.json" theirs ours
  [ -f "$record" ] || die "--restore $restore is not a long run's save (no run.json)"
  [ -n "$(find "$restore/carry" -type f -print -quit 2>/dev/null)" ] ||
    die "--restore $restore carries nothing (save the run with --carry PATH)"
  theirs=$(python3 -c 'import json, sys; r = json.load(open(sys.argv[1]))
print(r["commit"], r["profile"], "|", *sorted(r["settings"]))' "$record" 2>/dev/null) ||
    die "--restore $restore: its run.json is not a long run's record"
  # `save` records the settings split on spaces: compare them so, in any order
  ours=$(python3 -c 'import sys; print(sys.argv[1], sys.argv[2], "|", *sorted(" ".join(sys.argv[3:]).split()))' \
    "$rev" "${profile:-params.yaml of the commit}" "${settings[@]}")
  [ "$theirs" = "$ours" ] || die "--restore $restore is another run's (commit, profile | settings: $theirs; this run: $ours)"
}

launch_after() {  # launch once the run in $after has finished (a waiter in the background, its pid the run's)
  if finished "$after"; then launch; return; fi
  if pid=$(running_pid); then die "$folder is already running (pid $pid)"; fi
  echo "$after" > "$folder/long_run.after"
  setsid nohup bash "$0" _after "$folder" >> "$folder/long_run.log" 2>&1 < /dev/null &
  echo $! > "$folder/long_run.pid"
  echo "waiting in the background (pid $!) for $after to finish, then it runs: bash scripts/long_run.sh status $folder"
}

case $action in
  start)
    [ ! -e "$folder" ] || die "$folder exists: continue it with 'bash scripts/long_run.sh resume $folder'"
    [ -z "$after" ] || check_after
    rev=$(git -C "$source" rev-parse --verify "$commit^{commit}") || die "no commit $commit in $source"
    [ -z "$script" ] || git -C "$source" cat-file -e "$rev:$script" 2>/dev/null || die "no script $script at $rev"
    [ -z "$restore" ] || check_restore
    git clone -q "$source" "$folder"
    git -C "$folder" checkout -q "$rev"
    printf 'long_run.log\nlong_run.pid\nlong_run.rc\nlong_run.after\n.long_run.env\n' >> "$folder/.git/info/exclude"
    printf 'LONG_RUN_VENV=%q\nLONG_RUN_PROFILE=%q\nLONG_RUN_SCRIPT=%q\nLONG_RUN_SETTINGS=%q\n' "$venv" \
      "${profile:-params.yaml of the commit}" "$script" "${settings[*]}" > "$folder/.long_run.env"
    if [ -z "$venv" ]; then (cd "$folder" && bash scripts/setup.sh); fi
    if [ -n "$profile" ]; then (environment && cd "$folder" && adaptdiffuser profile "$profile"); fi
    if [ ${#settings[@]} -gt 0 ]; then (environment && cd "$folder" && adaptdiffuser set "${settings[@]}"); fi
    echo "pinned $folder at $rev"
    if [ -n "$restore" ]; then
      # the saved lock first: a carried output of a stage it records as finished makes DVC skip that stage
      [ ! -f "$restore/dvc.lock" ] || cp "$restore/dvc.lock" "$folder/dvc.lock"
      cp -r "$restore/carry/." "$folder/"
      echo "restored from $restore: $(python3 -c 'import json, sys; print(*json.load(open(sys.argv[1]))["carried"])' \
        "$restore/run.json") ($(find "$restore/carry" -type f | wc -l) files)"
      # DVC counts an output that is not in its cache as changed: put each carried one that is as the lock records
      # it there (an output that differs stays out, and its stage reruns)
      (environment && cd "$folder" && python - <<'EOF'
from dvc.repo import Repo

with Repo(".") as repo:
    for stage in repo.index.stages:
        for out in stage.outs:
            if out.use_cache and out.hash_info and out.exists and not out.changed_checksum() and out.changed_cache():
                out.commit()
                print(f"in DVC's cache: {out} ({stage.addressing})")
EOF
      )
    fi
    if [ -n "$after" ]; then launch_after; else launch; fi
    ;;
  resume)
    [ -f "$folder/.long_run.env" ] || die "$folder is not a long run (start one with 'long_run.sh start')"
    if [ -n "$after" ]; then check_after && launch_after; else launch; fi
    ;;
  _after)  # the waiter of launch_after: in the background, in a session of its own whose leader it stays
    other=$(cat "$folder/long_run.after")
    while running_pid "$other" > /dev/null; do sleep "${LONG_RUN_POLL_S:-10}"; done
    rm -f "$folder/long_run.after"
    if ! finished "$other"; then
      echo "== $(date -u +%FT%TZ) not started: $other was stopped or failed (resume this run to start it)"
      exit 1
    fi
    echo "== $(date -u +%FT%TZ) $other has finished"
    exec bash "$0" resume "$folder" --foreground
    ;;
  status)
    [ -f "$folder/.long_run.env" ] || die "$folder is not a long run"
    environment
    cd "$folder"
    echo "commit: $(git log -1 --format='%h %s' | cut -c1-100)"
    echo "profile: $LONG_RUN_PROFILE${LONG_RUN_SETTINGS:+, set: $LONG_RUN_SETTINGS}"
    echo "runs: ${LONG_RUN_SCRIPT:-dvc repro}"
    total=$(dvc stage list --name-only | wc -l)
    if pid=$(running_pid) && [ -f long_run.after ]; then
      echo "waiting: pid $pid, for $(cat long_run.after) to finish, then it runs; $total stages"
    elif pid=$(running_pid); then
      # DVC holds the repository's lock while it runs: the stages it started, from its log
      started=$(grep -c "^Running stage" long_run.log || true)
      echo "running: pid $pid; $total stages, $started started by this run's log, the last: $(grep "^Running stage" long_run.log | tail -n 1)"
    else
      left=$(dvc status --json | python -c 'import json, sys; print(len(json.load(sys.stdin)))')
      if finished "$folder"; then
        # a script that sets params between its passes (science_maze.sh) can end with stages not matching the params
        # it leaves: the run still ended by itself, with its results written
        echo "finished: ended by itself with exit status 0; $((total - left)) of $total stages match params.yaml, $left left"
      else
        ended=""; [ -f long_run.rc ] && ended=" (ended with exit status $(cat long_run.rc))"
        echo "not running$ended: $((total - left)) of $total stages done, $left left (continue: bash scripts/long_run.sh resume $folder)"
      fi
    fi
    # each training's resume state and the step it holds (a finished seed's state stays until its stage ends)
    python - <<'EOF' || true
from pathlib import Path

import torch

for state in sorted(Path("models/.resume").glob("*.pt")):
    if not state.name.startswith("."):  # not an atomic write's temporary file
        try:
            step = torch.load(state, map_location="cpu", weights_only=False)["step"]
        except Exception as err:  # a state being replaced, or from another torch: say so and go on
            step = f"unreadable: {err.__class__.__name__}"
        print(f"resume state: {state.name} (step {step})")
for record in sorted(Path("models/.resume").glob("*/record.json")):  # an evaluation's finished training seeds
    print(f"evaluated: {record.parent.name}")
EOF
    # progress bars rewrite their line with carriage returns: show each bar's latest state only
    tail -c 20000 long_run.log 2>/dev/null | sed 's/.*\r//' | tail -n 5 | sed 's/^/log: /' || true
    ;;
  stop)
    [ -f "$folder/.long_run.env" ] || die "$folder is not a long run"
    pid=$(running_pid) || die "$folder is not running"
    kill -TERM -- "-$pid" 2>/dev/null || kill -TERM "$pid"   # the run's process group (setsid): DVC and its stage
    kill -CONT -- "-$pid" 2>/dev/null || true                  # a paused (SIGSTOP) stage must run to take the TERM
    # a training stage ends its step and writes its resume state before it goes (stop_signals.py): wait for them all
    for _ in $(seq 30); do group_alive "$pid" || break; sleep 1; done
    if group_alive "$pid"; then kill -KILL -- "-$pid" 2>/dev/null || kill -KILL "$pid" 2>/dev/null || true; fi
    echo "stopped $folder (continue: bash scripts/long_run.sh resume $folder)"
    ;;
  save)
    [ -f "$folder/.long_run.env" ] || die "$folder is not a long run"
    # shellcheck disable=SC1091
    source "$folder/.long_run.env"
    dest=${into:-$here/metrics/runs/$(basename "$folder")}
    # replace only an earlier save of this same run (commit and profile): never another run's measurements
    if [ -e "$dest" ]; then
      ours="$(git -C "$folder" rev-parse HEAD) $LONG_RUN_PROFILE"
      theirs=$(python3 -c 'import json, sys; r = json.load(open(sys.argv[1])); print(r["commit"], r["profile"])' \
        "$dest/run.json" 2>/dev/null) || theirs="(no run.json)"
      [ "$theirs" = "$ours" ] || die "$dest holds other measurements (run: $theirs): save into a folder of its own, --into DIR"
    fi
    carried=()   # inside the run (not the clone's git, not long_run's own files), holding files: refused first
    for path in "${carry[@]}"; do
      rel=$(realpath -m --relative-to="$folder" "$folder/$path")
      case /$path:$rel in
        //*|*:.|*:..|*:../*|*:.git|*:.git/*|*:long_run.*|*:.long_run.env) die "--carry $path: not a path of the run's own files" ;;
      esac
      [ -e "$folder/$rel" ] || die "--carry $path: no such file or folder in $folder"
      [ -n "$(cd "$folder" && find "./$rel" -type f ! -name '.*' -print -quit)" ] || die "--carry $path: holds no file"
      carried+=("$rel")
    done
    running=false
    if running_pid > /dev/null; then running=true; fi
    # whole or absent: build beside the destination, then swap it in
    mkdir -p "$(dirname "$dest")"
    tmp=$(mktemp -d "$dest.XXXXXX")
    trap 'rm -rf "$tmp"' EXIT
    # the run's own: files of metrics/ that the pinned commit does not hold as they are now
    (cd "$folder" && git ls-files --others --modified -z -- metrics | sort -zu |
      while IFS= read -r -d '' file; do [ ! -f "$file" ] || cp --parents "$file" "$tmp/"; done)
    for file in params.yaml dvc.lock; do [ ! -f "$folder/$file" ] || cp "$folder/$file" "$tmp/$file"; done
    # what it carries: whole files (a resume state is replaced by a rename, never rewritten in place), no atomic
    # writes' hidden temporary files; a file that goes while this runs (its finished stage removed it) is left out
    [ ${#carried[@]} = 0 ] || mkdir "$tmp/carry"
    for rel in "${carried[@]}"; do
      (cd "$folder" && find "./$rel" -type f ! -name '.*' -print0 |
        while IFS= read -r -d '' file; do cp --parents "$file" "$tmp/carry/" || [ ! -e "$file" ]; done)
    done
    # the CPU it ran on (fine-tuned results differ in their last digits from one CPU to another); its cores by
    # getconf, not nproc, which counts OMP_NUM_THREADS
    cpu="$(sed -n 's/^model name[[:space:]]*: //p' /proc/cpuinfo | head -1), $(getconf _NPROCESSORS_ONLN) cores"
    if grep -qw avx512f /proc/cpuinfo; then cpu="$cpu, AVX-512"; else cpu="$cpu, no AVX-512"; fi
    python3 -c 'import json, sys; keys = "commit", "profile", "settings", "runs", "saved_at", "running", "cpu"
record = dict(zip(keys, sys.argv[1:])) | {"settings": sys.argv[3].split(), "running": sys.argv[6] == "true"}
print(json.dumps(record | {"carried": sys.argv[8:]}, indent=2))' \
      "$(git -C "$folder" rev-parse HEAD)" "$LONG_RUN_PROFILE" "${LONG_RUN_SETTINGS:-}" "${LONG_RUN_SCRIPT:-dvc repro}" \
      "$(date -u +%FT%TZ)" "$running" "$cpu" "${carried[@]}" > "$tmp/run.json"
    had_carry=0; [ ! -d "$dest/carry" ] || had_carry=1
    rm -rf "$dest.old"
    if [ -e "$dest" ]; then mv "$dest" "$dest.old"; fi
    mv "$tmp" "$dest"
    rm -rf "$dest.old"
    trap - EXIT
    echo "saved $folder's measurements in $dest ($(find "$dest" -path "$dest/metrics/*" -type f | wc -l) files of metrics/; commit them)"
    if [ ${#carried[@]} -gt 0 ]; then
      echo "carried: ${carried[*]} ($(find "$dest/carry" -type f | wc -l) files, $(du -sh "$dest/carry" | cut -f1))"
    elif [ "$had_carry" = 1 ]; then
      echo "note: the earlier save's carry/ is not in this one (save with --carry PATH to keep a run's training)"
    fi
    ;;
  *) usage ;;
esac
