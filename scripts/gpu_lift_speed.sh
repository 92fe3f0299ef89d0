#!/usr/bin/env bash
# Builds only what the lift/sampling speed work needs on the GPU machine (bench_lift, bench_stage1,
# bench_mesh, test_models_gpu), runs the flow model's GPU tests, then the benchmarks, logs under $OUT
# (or ./bench-out). Needs .carry/ as scripts/gpu_build_test.sh does. Writes BUILD_DIR (../build-gpu-lift).
#   device run (carry .carry): bash scripts/gpu_lift_speed.sh [quick]
# quick: the headline bench_lift and bench_stage1 rows only.
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
O="${OUT:-$ROOT/bench-out}"
mkdir -p "$O"
source "$ROOT/scripts/gpu_env.sh"
B="${BUILD_DIR:-$ROOT/../build-gpu-lift}"
t0=$(date +%s)
gpu_configure "$B" "$O/build.log" || exit 1
cmake --build "$B" -j"$(nproc)" --target bench_lift bench_stage1 bench_mesh test_models_gpu >>"$O/build.log" 2>&1 \
  || { grep -B2 -A12 -E "error|FAILED" "$O/build.log" | head -80; exit 1; }
echo "[gpu] configure+build: $(( $(date +%s) - t0 )) s on $(nproc) cores"
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,temperature.gpu --format=csv,noheader || true
run() { local name="$1"; shift; echo "== $name: $*"; local s=$(date +%s); "$@" >"$O/$name.txt" 2>&1; echo "   rc $? in $(( $(date +%s) - s )) s"; }
run tests "$B/test_models_gpu" --gtest_filter='FlowModelGpu.*:FusedOpsGpu.*:PrecisionGpu.*'
grep -E "^\[  (PASSED|FAILED) |FAILED|tests ran|Failure|Expected|Which is|actual" "$O/tests.txt" | head -30
# lift: the default path (eager launches), then persistent CUDA graphs in a fresh process (first call apart).
run lift "$B/bench_lift" --device cuda --batches 1 8 --iters 3 --precision fp16 --diagnose
[ "${1:-}" != quick ] && run lift_graphs "$B/bench_lift" --device cuda --batches 1 8 --iters 3 --precision fp16 --graphs on
if [ "${1:-}" != quick ]; then
  run mesh "$B/bench_mesh" --threads 1 0
  fi
run stage1 "$B/bench_stage1" --precision fp16 --cond-lens 7528 2800 --captures ${CAPTURES:-overlap} --sample-iters "${SAMPLE_ITERS:-3}"
[ "${PROFILE:-0}" = 1 ] && run profile "$B/bench_stage1" --precision fp16 --cond-lens 7528 2800 --iters 2 --sample-iters 1 --warmup 1 --profile --captures overlap
for f in lift lift_graphs; do [ -f "$O/$f.txt" ] && { echo "-- $f"; grep -E "^\||diagnose|first call|call [0-9]" "$O/$f.txt" | grep -v "^|---"; }; done
[ -f "$O/mesh.txt" ] && grep -E "^random|^sphere|^case" "$O/mesh.txt"
echo "-- stage1"; grep -E "^\||matmul" "$O/stage1.txt" | grep -v "^|---"
exit 0
