#!/usr/bin/env bash
# Maze2D Large's phase-0 learning curves on a lent GPU machine (docs/speed.md#on-a-gpu-the-paper-large-shapes-on-one-h100):
# `paper-large` (the paper's shapes) and `science-large` (the CPU profile's, to choose its pretraining steps), side by
# side on one GPU, scored on validation episodes (seed 7) as they train, until a wall-clock deadline.
#
#   bash scripts/gpu_curves.sh prepare [--steps N] [--python 3.12]
#       here, before asking for a machine (about 10 min on 2 cores): into gpu/ (git-ignored) the two workspaces
#       sharing one expert dataset of N steps (default 1e6: the profiles' 4e6 would not travel within the 64 MiB a
#       call carries) and its reference, and gpu/site.tgz, the Python packages the curves import that a CUDA PyTorch
#       image lacks, built for that image's Python
#   bash scripts/gpu_curves.sh run [--deadline SECONDS] [--out DIR] [--device cuda]
#       there, with gpu/ carried (the device tool: command `bash scripts/gpu_curves.sh run`, carry ["gpu"]): unpack the
#       packages, train paper-large (training seed 0) and science-large (training seeds 0 and 1) at once with eager
#       float32 (compiling gains about 1.1x on a GPU at these sizes), each stopped at the deadline (default 450 s
#       from the start); every point goes to DIR (default $OUT) as measured, with the machine's facts and log tails
#       (`prepare --python 3.11` and `run --device cpu` with this repository's .venv first on PATH check the plumbing
#       here)
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
cd "$here"
die() { echo "gpu_curves: $*" >&2; exit 2; }
[ $# -ge 1 ] || { sed -n '2,17p' "$0" >&2; exit 2; }
action=$1; shift
steps=1000000 python_version=3.12 deadline=450 out="${OUT:-}" device=cuda
while [ $# -gt 0 ]; do
  case $1 in
    --steps) steps=$2; shift 2 ;;
    --python) python_version=$2; shift 2 ;;
    --deadline) deadline=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    --device) device=$2; shift 2 ;;
    *) die "unknown option $1" ;;
  esac
done
task=maze2d-large
curve="benchmarks/learning_curve.py"

# What the curves import beyond a CUDA PyTorch image with numpy, pandas, pyarrow, matplotlib, PyYAML, tqdm, requests
# (read from the modules a CPU curve loads; mujoco-studio, OpenGL and gymnasium-robotics' robot meshes are left out:
# nothing here renders).
extra_packages=(mlflow-skinny mlflow-tracing databricks-sdk google-auth pyasn1 pyasn1_modules cachetools fastapi
  starlette orjson pydot sqlparse importlib_metadata protobuf opentelemetry-api opentelemetry-proto opentelemetry-sdk
  opentelemetry-semantic-conventions pydantic pydantic_core annotated-types typing-inspection typing_extensions
  mujoco mujoco-core gymnasium gymnasium-robotics Farama-Notifications PettingZoo wcwidth cffi pycparser glfw)

prepare() {
  local py="$here/.venv/bin/python" cli="$here/.venv/bin/adaptdiffuser"
  [ -x "$cli" ] || die "no .venv here: run bash scripts/setup.sh first"
  mkdir -p gpu
  local ws
  for ws in paper science; do
    mkdir -p "gpu/ws-$ws"
    (cd "gpu/ws-$ws" && "$cli" profile "$ws-large" --params params.yaml --profiles-dir "$here/profiles" >/dev/null)
    "$cli" set --params "gpu/ws-$ws/params.yaml" "task.$task.collect.steps=$steps" compile.training=false \
      compile.sampling=false > /dev/null
  done
  if [ ! -f gpu/ws-paper/data/$task/dataset.parquet ] || [ "$(cat gpu/steps 2>/dev/null)" != "$steps" ]; then
    (cd gpu/ws-paper && OMP_NUM_THREADS=1 "$cli" collect --task $task --no-progress && "$cli" reference --task $task)
    echo "$steps" > gpu/steps
  fi
  local wheels site
  wheels=$(mktemp -d) site=$(mktemp -d)
  local pins=() p v
  for p in "${extra_packages[@]}"; do
    v=$("$py" -m pip show "$p" 2>/dev/null | awk '/^Version:/{print $2}')
    [ -n "$v" ] || die "$p is not installed here: run bash scripts/setup.sh --dev"
    pins+=("$p==$v")
  done
  local platform=(--python-version "$python_version" --implementation cp --only-binary=:all:
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64
    --platform manylinux2014_x86_64)
  "$py" -m pip download -q --no-deps "${platform[@]}" -d "$wheels" "${pins[@]}"
  "$py" -m pip install -q --no-deps --no-index --no-compile --target "$site" "${platform[@]}" "$wheels"/*.whl
  rm -rf "$site"/gymnasium_robotics/envs/assets/{adroit_hand,hand,kitchen_franka,stls,textures,fetch} "$site"/bin
  tar czf gpu/site.tgz.tmp -C "$site" . && mv gpu/site.tgz.tmp gpu/site.tgz
  # what a run (here, with --device cpu) leaves: models, and the second workspace's copy of the data, which would
  # not travel within the limit
  rm -rf "$wheels" "$site" gpu/ws-*/models gpu/ws-*/mlflow.db gpu/ws-*/mlflow-pending gpu/ws-science/data \
    gpu/ws-science/metrics
  echo "gpu/ ready ($(du -sh gpu | cut -f1); a call carries 64 MiB with the repository): on the lent machine run"
  echo "  bash scripts/gpu_curves.sh run    (device tool, carry [\"gpu\"])"
}

run() {
  local t0 left
  t0=$(date +%s)
  [ -n "$out" ] || die "no --out and no \$OUT"
  [ -f gpu/site.tgz ] || die "gpu/site.tgz is missing: run 'bash scripts/gpu_curves.sh prepare' here and carry gpu"
  export PYTHONUNBUFFERED=1
  mkdir -p /tmp/site "$out" && tar xzf gpu/site.tgz -C /tmp/site
  export PYTHONPATH="/tmp/site:$here/src"
  python3 -c "import adaptdiffuser.stages.pretrain, adaptdiffuser.families.maze2d.point_mass, gymnasium_robotics, mlflow" \
    || die "an import failed on this machine (above): add its package to extra_packages and prepare again"
  { date -u; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
    lscpu | grep -E "Model name|^CPU\(s\)"
    python3 -c "import sys, torch, mujoco; print(sys.version); print('torch', torch.__version__, 'mujoco', mujoco.__version__)"
  } > "$out/machine.txt" 2>&1 || true
  cp -r gpu/ws-paper/data gpu/ws-science/
  mkdir -p gpu/ws-science/metrics && cp -r gpu/ws-paper/metrics/tasks gpu/ws-science/metrics/
  left=$((deadline - ($(date +%s) - t0)))
  echo "setup $(($(date +%s) - t0)) s; training wall $left s" >> "$out/machine.txt"
  local pids=() s
  OMP_NUM_THREADS=4 timeout -s TERM "$left" python3 "$curve" gpu/ws-paper --task $task --steps 2000000 --every 2000 \
    --episodes 30 --training-seed 0 --device "$device" --out "$out/paper-large-seed0.jsonl" > /tmp/paper-large-seed0.log 2>&1 &
  pids+=($!)
  for s in 0 1; do
    OMP_NUM_THREADS=4 timeout -s TERM "$left" python3 "$curve" gpu/ws-science --task $task --steps 40000 --every 2000 \
      --episodes 30 --training-seed $s --device "$device" --out "$out/science-large-seed$s.jsonl" \
      > "/tmp/science-large-seed$s.log" 2>&1 &
    pids+=($!)
  done
  (while sleep 20; do nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader; done) \
    > /tmp/gpu-utilization.txt 2>&1 &
  wait "${pids[@]}" || true
  for f in /tmp/paper-large-seed0.log /tmp/science-large-seed0.log /tmp/science-large-seed1.log /tmp/gpu-utilization.txt; do
    echo "== $f"; tr '\r' '\n' < "$f" | grep -v '^\s*$' | tail -30
  done > "$out/logs.txt"
  cat "$out"/*.jsonl 2>/dev/null || true
  echo "total $(($(date +%s) - t0)) s"
}

case $action in
  prepare) prepare ;;
  run) run ;;
  *) die "unknown action $action (prepare or run)" ;;
esac
