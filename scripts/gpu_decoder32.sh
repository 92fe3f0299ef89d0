#!/usr/bin/env bash
# The 32^3 decoder of docs/rules/decoder32.md on one GPU: the shipped encoder (weights/miniature_cpu)
# frozen, a SparseStructureDecoder with one more up-sampling level trained against the shape world's
# 32^3 occupancy (train_ss_vae --config configs/miniature_cpu/ss_decoder32.yaml). Device calls of at most
# ~10 minutes continue each other while the machine stays warm: the build is skipped when present in
# $STATE (repo-ignored; kept between calls), training resumes from its last checkpoint, and each call
# stops before its deadline (run.stop_after_s) and packs what exists into $OUT.
#   device run on nvidia-h200 (carry .carry/prefix/usr/{include,lib/x86_64-linux-gnu,lib/libgloo.so,share,src}):
#     DEADLINE_S=560 bash scripts/gpu_decoder32.sh
# Knobs: STEPS (train.steps, default the config's), EXTRA="--set k=v ..." (more train_ss_vae overrides).
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
t0=$(date +%s)
source "$ROOT/scripts/gpu_env.sh"
OUTD="${OUT:-/tmp/gpu_dec32_out}"
mkdir -p "$OUTD"
DEADLINE="${DEADLINE_S:-560}"
read -r -a EXTRA_ARGS <<<"${EXTRA:-}"
STATE="$ROOT/${STATE_DIR:-runs/gpu_dec32}"
BUILD="$STATE/build"
RUN="$STATE/dec32"
LOG="$OUTD/call.log"
mkdir -p "$STATE"
elapsed() { echo $(( $(date +%s) - t0 )); }
say() { echo "[gpu $(elapsed) s] $*" | tee -a "$LOG"; }
say "start; state: $(ls "$STATE" | tr '\n' ' ')"

# 1. Build (once per machine).
if [ ! -x "$BUILD/train_ss_vae" ]; then
  gpu_configure "$BUILD" "$OUTD/configure.log" -DSIMU_BUILD_TESTS=OFF -DSIMU_BUILD_PYTHON=OFF -DSIMU_CUDA_KERNELS=OFF || exit 1
  ninja -C "$BUILD" train_ss_vae >"$OUTD/build.log" 2>&1 || { grep -B2 -A8 -E "error|FAILED" "$OUTD/build.log" | head -60; exit 1; }
  say "built on $(nproc) cores"
fi
nvidia-smi --query-gpu=index,name,memory.total --format=csv,noheader | tee -a "$LOG"

# 2. Train (resumed when a checkpoint exists) until the steps are done or the deadline nears (packing ~20 s).
left=$(( DEADLINE - $(elapsed) - 40 ))
if [ ! -f "$RUN/eval.json" ] && [ "$left" -gt 30 ]; then
  resume=(); [ -d "$RUN/checkpoints" ] && resume=(--resume latest)
  steps=(); [ -n "${STEPS:-}" ] && steps=(--set "train.steps=$STEPS")
  "$BUILD/train_ss_vae" --config configs/miniature_cpu/ss_decoder32.yaml "${resume[@]}" "${steps[@]}" \
    --set "run.out_dir=$RUN" --set "run.stop_after_s=$left" --set run.progress=false "${EXTRA_ARGS[@]}" \
    >>"$STATE/dec32.log" 2>&1 || say "train_ss_vae failed: $(tail -n 5 "$STATE/dec32.log")"
fi
say "decoder: $(tail -n 1 "$RUN/metrics.jsonl" 2>/dev/null | cut -c1-300)"
[ -f "$RUN/eval.json" ] && say "done, test IoU: $(python3 -c "import json; j = json.load(open('$RUN/eval.json'))['iou']; print('seen', j['seen'], 'held out', j['held_out'])")"

# 3. What comes back.
cd "$STATE"
have=()
for f in dec32.log dec32/metrics.jsonl dec32/eval.json dec32/weights; do [ -e "$f" ] && have+=("$f"); done
tar czf "$OUTD/dec32_back.tgz" "${have[@]}"
say "packed: $(du -sh "$OUTD/dec32_back.tgz" | cut -f1) (${#have[@]} items)"
