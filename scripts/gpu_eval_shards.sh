#!/usr/bin/env bash
# eval_lift in parallel shards on the GPU machine's CPU cores (one thread each), for models side by side
# (docs/results.md): builds eval_lift once, then runs every line of a job file, `NAME MODEL_DIR ARGS...`,
# as `eval_lift ARGS --out $OUT/NAME` with the model folder's configs and weights, $(nproc) at a time.
# Merge the shards with scripts/merge_eval_shards.py. The device returns only a few files per call, so
# every summary.json is packed into $OUT/summaries.tgz. Locally: EVAL_BUILD=build PARALLEL=2 OUT=DIR.
#   device run (carry .carry/prefix/usr/{include,lib/x86_64-linux-gnu,lib/libgloo.so,share,src}):
#     JOBS_FILE=runs/eval_jobs.txt bash scripts/gpu_eval_shards.sh
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
source "$ROOT/scripts/gpu_env.sh"
OUTD="${OUT:-/tmp/gpu_eval_out}"
mkdir -p "$OUTD"
BUILD="${EVAL_BUILD:-$ROOT/runs/gpu_eval_build}"
t0=$(date +%s)
if [ ! -x "$BUILD/eval_lift" ]; then
  gpu_configure "$BUILD" "$OUTD/configure.log" -DSIMU_BUILD_TESTS=OFF -DSIMU_BUILD_PYTHON=OFF -DSIMU_CUDA_KERNELS=OFF || exit 1
  ninja -C "$BUILD" eval_lift >"$OUTD/build.log" 2>&1 || { grep -B2 -A8 -E "error|FAILED" "$OUTD/build.log" | head -60; exit 1; }
fi
echo "[gpu $(( $(date +%s) - t0 )) s] built; $(wc -l <"$JOBS_FILE") jobs on $(nproc) cores"
run_job() {
  local name="$1" model="$2"; shift 2
  OMP_NUM_THREADS=1 timeout "${JOB_TIMEOUT_S:-500}" "$BUILD/eval_lift" "$@" --threads 1 --no-pictures --device cpu \
    --generator-config "$model/generator.yaml" --generator-weights "$model/ss_generator.safetensors" \
    --embedder-config "$model/embedder.json" --embedder-weights "$model/ss_generator.safetensors" \
    --decoder-config "$model/ss_decoder.json" --decoder-weights "$model/ss_decoder.safetensors" \
    --preprocess "$model/preprocess.yaml" --out "$OUTD/$name" --overwrite >"$OUTD/$name.log" 2>&1 ||
    echo "job $name failed: $(tail -n 2 "$OUTD/$name.log")"
}
export -f run_job
export BUILD OUTD
xargs -P "${PARALLEL:-$(nproc)}" -L 1 bash -c 'run_job "$@"' _ <"$JOBS_FILE"
(cd "$OUTD" && tar czf summaries.tgz $(ls -d */summary.json 2>/dev/null))
echo "[gpu $(( $(date +%s) - t0 )) s] done: $(ls "$OUTD"/*/summary.json 2>/dev/null | wc -l) summaries -> $OUTD/summaries.tgz"
