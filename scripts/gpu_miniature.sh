#!/usr/bin/env bash
# The miniature (configs/miniature by default) trained from nothing on one GPU, in device calls of at most
# ~10 minutes that continue each other while the machine stays warm (docs/miniature.md). Every stage
# is skipped when its output is already in $STATE (a repo-ignored folder the machine keeps between
# calls), and each call stops before its own deadline:
#   1. configure and build the programs (skipped when built);
#   2. train_ss_vae (VAE_STEPS) beside build_stage1_data (SCENES train scenes on the other cores);
#   3. bench_train_stage1 once: the measured rate sizes train.steps for TRAIN_S seconds of training
#      in all, over the calls (cosine schedule over those steps);
#   4. train_stage1 --resume latest until this call's deadline (a checkpoint at the stop);
#   5. when the steps are done: ship the folder (scripts/ship_miniature.py) and eval_lift on the test
#      split (EVAL_COUNT objects, clean and corrupted point maps) and the held-out family;
#   6. pack what comes back into $OUT (metrics, logs, the run's exports, evaluations; <= 15 MB parts).
#   device run (carry .carry/prefix), the same command each call:
#     DEADLINE_S=560 bash scripts/gpu_miniature.sh
# Environment: CONFIG_DIR (configs/miniature), RESOLUTION (32), SCENES, BATCH, TRAIN_S, STEP_FACTOR,
# VAE_STEPS, EVAL_COUNT (0: no evaluation on the device), STATE_DIR (runs/gpu_mini), and VAE_FROM: a
# train_ss_vae output (its weights/ folder, carried) whose frozen encoder and decoder are used instead of
# training a VAE (the CPU miniature's own, runs/ss_vae_cpu, for its GPU retraining):
#   CONFIG_DIR=configs/miniature_cpu RESOLUTION=16 SCENES=25000 BATCH=128 VAE_FROM=runs/ss_vae_cpu \
#     STATE_DIR=runs/gpu_mini16 EVAL_COUNT=0 DEADLINE_S=560 bash scripts/gpu_miniature.sh
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
t0=$(date +%s)
source "$ROOT/scripts/gpu_env.sh"
OUTD="${OUT:-/tmp/gpu_miniature_out}"
mkdir -p "$OUTD"
CFG="${CONFIG_DIR:-configs/miniature}"
DEADLINE="${DEADLINE_S:-560}"   # seconds from this script's start to the end of its packing
SCENES="${SCENES:-20000}"
VAE_STEPS="${VAE_STEPS:-2000}"
TRAIN_S="${TRAIN_S:-950}"       # stage-1 training seconds over all calls (sizes train.steps)
BATCH="${BATCH:-256}"
EVAL_COUNT="${EVAL_COUNT:-500}"
RES="${RESOLUTION:-32}"
STATE="$ROOT/${STATE_DIR:-runs/gpu_mini}"
BUILD="$STATE/build"
LOG="$OUTD/call.log"
mkdir -p "$STATE"
elapsed() { echo $(( $(date +%s) - t0 )); }
say() { echo "[gpu $(elapsed) s] $*" | tee -a "$LOG"; }
say "start; state: $(ls "$STATE" | tr '\n' ' ')"

# 1. Build (once per machine).
if [ ! -x "$BUILD/train_stage1" ] || [ ! -x "$BUILD/eval_lift" ]; then
  gpu_configure "$BUILD" "$OUTD/configure.log" -DSIMU_BUILD_TESTS=OFF -DSIMU_BUILD_PYTHON=OFF -DSIMU_CUDA_KERNELS=OFF || exit 1
  ninja -C "$BUILD" train_ss_vae build_stage1_data train_stage1 bench_train_stage1 eval_lift >"$OUTD/build.log" 2>&1 ||
    { grep -B2 -A8 -E "error|FAILED" "$OUTD/build.log" | head -60; exit 1; }
  say "built on $(nproc) cores"
fi
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee -a "$LOG"

# 2. The VAE (GPU, 8 data workers) beside the stage-1 cache (the remaining cores).
VAE="$STATE/ss_vae"
vae_pid=""
if [ -n "${VAE_FROM:-}" ] && [ ! -f "$VAE/weights/ss_encoder.safetensors" ]; then
  [ -f "$VAE_FROM/weights/ss_encoder.safetensors" ] || { say "VAE_FROM=$VAE_FROM has no weights/ss_encoder.safetensors (carry it)"; exit 1; }
  mkdir -p "$VAE" && cp -r "$VAE_FROM/weights" "$VAE/" && { [ -f "$VAE_FROM/eval.json" ] && cp "$VAE_FROM/eval.json" "$VAE/" || true; }
  say "vae: from $VAE_FROM (not trained here)"
fi
if [ ! -f "$VAE/weights/ss_encoder.safetensors" ]; then
  "$BUILD/train_ss_vae" --config "$CFG/ss_vae.yaml" --set "train.steps=$VAE_STEPS" --set run.out_dir="$VAE" \
    --set run.progress=false --set run.log_every=100 --set eval.every="$VAE_STEPS" --overwrite >"$STATE/vae.log" 2>&1 &
  vae_pid=$!
fi
if [ ! -f "$STATE/stage1.h5" ]; then
  "$BUILD/build_stage1_data" --out "$STATE/stage1.h5" --train "$SCENES" --val 300 --test 0 \
    --preprocess "$CFG/preprocess.yaml" --resolution "$RES" --threads "$(( $(nproc) - 2 ))" >"$STATE/cache.log" 2>&1 ||
    { tail -5 "$STATE/cache.log"; exit 1; }
  say "cache: $(tail -n 1 "$STATE/cache.log")"
fi
if [ -n "$vae_pid" ]; then
  wait "$vae_pid" || { tail -20 "$STATE/vae.log"; exit 1; }
  say "vae: $(grep -o '"test/iou_seen":[0-9.]*\|"test/iou_held_out":[0-9.]*' "$VAE/metrics.jsonl" | tail -2 | tr '\n' ' ')"
fi
ENC="$VAE/weights"

# 3. The rate, once: sizes train.steps. The benchmark times the model's step on synthetic samples; the
#    real step also computes the frozen encoder's targets and decodes the batch: on 2026-11-29 it took
#    0.20 s against the benchmark's 0.099 s (configs/miniature, batch 256), hence STEP_FACTOR.
if [ ! -f "$STATE/steps" ]; then
  "$BUILD/bench_train_stage1" --config "$CFG/train_stage1.yaml" --device cuda --precision bf16 \
    --batch "$BATCH" --steps 20 --warmup 5 --resolution "$RES" | tee "$STATE/bench_train_stage1.txt"
  rate=$(awk -F'|' '/^\| cuda/ {gsub(/ /, "", $8); print $8}' "$STATE/bench_train_stage1.txt" | tail -n 1)
  python3 -c "print(max(100, int(0.85 * $TRAIN_S * float('$rate') / $BATCH / ${STEP_FACTOR:-2.0})))" >"$STATE/steps"
  say "rate $rate samples/s: train.steps $(cat "$STATE/steps") for $TRAIN_S s"
fi
STEPS=$(cat "$STATE/steps")

# 4. Stage 1 until this call's deadline (what is left after packing, ~40 s, and the evaluation's ~150 s
#    when the steps would end in this call).
RUN="$STATE/stage1"
if [ ! -d "$RUN/model" ]; then
  left=$(( DEADLINE - $(elapsed) - 40 ))
  resume=()
  [ -d "$RUN/checkpoints" ] && resume=(--resume latest)
  "$BUILD/train_stage1" --config "$CFG/train_stage1.yaml" "${resume[@]}" \
    --set train.device=cuda --set train.precision=bf16 --set "data.global_batch=$BATCH" --set "data.micro_batch=$BATCH" \
    --set "train.steps=$STEPS" --set data.cache="$STATE/stage1.h5" --set run.out_dir="$RUN" \
    --set "targets.encoder_config=$ENC/ss_encoder.json" --set "targets.encoder_weights=$ENC/ss_encoder.safetensors" \
    --set run.checkpoint_every=1000 --set "run.stop_after_s=$left" --set run.log_every=100 --set run.progress=false \
    >>"$STATE/stage1.log" 2>&1 || { tail -20 "$STATE/stage1.log"; }
  say "stage1: $(grep -c '"step"' "$RUN/metrics.jsonl" 2>/dev/null) logged steps; last: $(tail -n 1 "$RUN/metrics.jsonl" | cut -c1-300)"
fi

# 5. Ship and evaluate once the steps are done.
if [ -d "$RUN/model" ] && [ ! -d "$STATE/miniature" ]; then
  python3 scripts/ship_miniature.py --vae "$VAE" --stage1 "$RUN" --out "$STATE/miniature" \
    --preprocess "$CFG/preprocess.yaml" >"$STATE/ship.log" 2>&1 || tail -5 "$STATE/ship.log"
fi
if [ -d "$RUN/model" ] && [ "$EVAL_COUNT" -gt 0 ] && [ ! -f "$STATE/eval_test/summary.json" ]; then
  for split in test heldout; do
    n=$EVAL_COUNT; [ "$split" = heldout ] && n=$(( EVAL_COUNT / 5 ))
    SIMU_DEFAULT_MODEL="$STATE/miniature" "$BUILD/eval_lift" --world "$split" --count "$n" --seed 0 --depth both \
      --device cuda --no-pictures --out "$STATE/eval_$split" --overwrite >"$STATE/eval_$split.log" 2>&1 ||
      tail -5 "$STATE/eval_$split.log"
    say "eval $split: $(tail -n 3 "$STATE/eval_$split.log" | tr '\n' ' ' | cut -c1-400)"
  done
fi

# 6. What comes back: one archive in parts of <= 15 MB (runs' metrics and logs; exports once made).
cd "$STATE"
items=(steps bench_train_stage1.txt vae.log cache.log stage1.log ss_vae/metrics.jsonl ss_vae/eval.json ss_vae/weights
       stage1/metrics.jsonl stage1/model miniature eval_test eval_heldout eval_test.log eval_heldout.log ship.log)
# No export yet: the newest checkpoint comes back instead (train_stage1 --resume latest --set
# train.steps=<its step> exports its EMA anywhere; ~56 MB, 4 parts).
if [ ! -d stage1/model ] && [ -d stage1/checkpoints ]; then items+=("$(ls -d stage1/checkpoints/step_* | sort -V | tail -n 1)"); fi
have=(); for i in "${items[@]}"; do [ -e "$i" ] && have+=("$i"); done
tar czf /tmp/mini_back.tgz "${have[@]}" && split -b 15M -d /tmp/mini_back.tgz "$OUTD/mini_back.tgz.part"
say "packed: $(du -sh /tmp/mini_back.tgz | cut -f1) (${have[*]})"
