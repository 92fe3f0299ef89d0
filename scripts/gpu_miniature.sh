#!/usr/bin/env bash
# Stage-1 pretraining of the CPU miniature (configs/miniature_cpu) on one GPU inside a fixed time budget,
# for a device call that holds one machine once: configure and build the two programs, build the stage-1
# cache on every core, measure the training rate (bench_train_stage1), size train.steps so that the run
# ends (with its EMA export) before the deadline, train, and copy the model and curves to $OUT.
#   device run (carry .carry/prefix runs/ss_vae_cpu/weights):
#     DEADLINE_S=270 SCENES=12000 bash scripts/gpu_miniature.sh
# Needs the frozen encoder of train_ss_vae (configs/miniature_cpu/ss_vae.yaml) in runs/ss_vae_cpu/weights.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
t0=$(date +%s)
source "$ROOT/scripts/gpu_env.sh"
OUTD="${OUT:-/tmp/gpu_miniature_out}"
mkdir -p "$OUTD"
DEADLINE="${DEADLINE_S:-270}"   # seconds from the start of this script to the end of the export
SCENES="${SCENES:-12000}"
BATCH="${BATCH:-256}"
BUILD=/tmp/build-gpu-miniature
ENC="$ROOT/runs/ss_vae_cpu/weights"
[ -f "$ENC/ss_encoder.safetensors" ] || { echo "error: $ENC/ss_encoder.safetensors missing (train_ss_vae, carried)" >&2; exit 1; }
elapsed() { echo $(( $(date +%s) - t0 )); }

gpu_configure "$BUILD" "$OUTD/configure.log" -DSIMU_BUILD_TESTS=OFF -DSIMU_BUILD_PYTHON=OFF -DSIMU_CUDA_KERNELS=OFF || exit 1
ninja -C "$BUILD" train_stage1 build_stage1_data bench_train_stage1 >"$OUTD/build.log" 2>&1 ||
  { grep -B2 -A8 -E "error|FAILED" "$OUTD/build.log" | head -60; exit 1; }
echo "[gpu] configure+build: $(elapsed) s on $(nproc) cores"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || true

# The cache: the same command as on the CPU but fewer scenes (the budget).
"$BUILD/build_stage1_data" --out /tmp/stage1.h5 --train "$SCENES" --val 300 --test 0 \
  --preprocess configs/miniature_cpu/preprocess.yaml --resolution 16 --threads "$(nproc)" 2>&1 | tail -n 2
echo "[gpu] cache: $(elapsed) s"

# The rate, on synthetic samples (bf16, batch $BATCH): the samples/s column of the table row.
"$BUILD/bench_train_stage1" --config configs/miniature_cpu/train_stage1.yaml --device cuda --precision bf16 \
  --batch "$BATCH" --steps 20 --warmup 5 --resolution 16 | tee "$OUTD/bench_train_stage1.txt"
rate=$(awk -F'|' '/^\| cuda/ {gsub(/ /, "", $8); print $8}' "$OUTD/bench_train_stage1.txt" | tail -n 1)
left=$(( DEADLINE - $(elapsed) - 20 ))
steps=$(python3 -c "print(max(50, int(0.8 * $left * float('$rate') / $BATCH)))")
echo "[gpu] rate $rate samples/s, $left s left: train.steps $steps"

"$BUILD/train_stage1" --config configs/miniature_cpu/train_stage1.yaml \
  --set train.device=cuda --set train.precision=bf16 --set "data.global_batch=$BATCH" --set "data.micro_batch=$BATCH" \
  --set "train.steps=$steps" --set data.cache=/tmp/stage1.h5 --set run.out_dir=/tmp/stage1_run \
  --set "targets.encoder_config=$ENC/ss_encoder.json" --set "targets.encoder_weights=$ENC/ss_encoder.safetensors" \
  --set run.checkpoint_every=0 --set "run.stop_after_s=$((left + 10))" --set run.log_every=100 --set run.progress=false 2>&1 | tail -n 5
echo "[gpu] trained: $(elapsed) s"
# The export; when the rate was misjudged and the safety stop came first, the checkpoint's EMA instead.
if [ -d /tmp/stage1_run/model ]; then cp -r /tmp/stage1_run/model "$OUTD/model"
else ck=$(ls -d /tmp/stage1_run/checkpoints/step_* | sort -V | tail -n 1); mkdir -p "$OUTD/checkpoint"
  cp "$ck"/{model,extra}.safetensors "$ck"/train_state.json "$OUTD/checkpoint/"; fi
cp /tmp/stage1_run/metrics.jsonl "$OUTD/"
ls -la "$OUTD"/model "$OUTD"/checkpoint 2>/dev/null || true
