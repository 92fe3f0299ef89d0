#!/usr/bin/env bash
# Two Stage-1 trainings side by side, one per GPU of a 2-GPU machine, plus FM-DPO of the shipped
# miniature on 1 and 2 ranks (issues 35 and 36; docs/miniature.md "Two more Stage-1 runs"). Device calls
# of at most ~10 minutes continue each other while the machine stays warm: every stage is skipped when
# its output is already in $STATE (repo-ignored; the machine keeps it between calls), and each call
# stops before its deadline.
#   1. configure and build the programs (skipped when built);
#   2. the stage-1 cache (build_stage1_data --train SCENES --val 300 --resolution 16 with the CPU
#      miniature's preprocessing and corrupted point maps) on all but 4 cores; meanwhile, on the idle
#      GPUs: bench_train_stage1 of each variant (sizes its train.steps for TRAIN_S seconds), then
#      FM-DPO of the shipped base (configs/miniature_cpu/lora.yaml, beta 50 as shipped, bf16, seed 0)
#      on 1 rank (micro-batch 8 x 2 accumulation) and on 2 ranks (micro-batch 8 each);
#   3. the variants' train_stage1 --resume latest in parallel (variant i on GPU i) until the deadline;
#   4. pack what comes back into $OUT (metrics, logs, benches, FM-DPO runs, and each variant's exported
#      model once its steps are done, to be shipped here by scripts/ship_miniature.py; <= 15 MB parts).
# Variants (VARIANTS="name:config_dir ..."): cpu = the shipped architecture (configs/miniature_cpu) with
# more samples; wide = configs/miniature_wide (flow model 128 ch x 4 blocks, embedder 96 ch x 3 blocks).
#   device run on nvidia-h200-x2, the same command each call (carry .carry/prefix/usr/{include,
#   lib/x86_64-linux-gnu,lib/libgloo.so,share,src}, runs/ss_vae_cpu/weights, data/pairs_cpu.h5):
#     DEADLINE_S=560 bash scripts/gpu_stage1_pair.sh
# Knobs for one model on both GPUs instead (the fourth Stage 1, docs/miniature.md): RANKS=2 runs the one
# variant data-parallel over 2 ranks (global batch BATCH x RANKS); STEPS=N fixes train.steps (no bench);
# INIT=FILE starts from those weights (model.init; carry the file); CACHE_SEED=S builds the cache from
# scene seed S (fresh scenes); EXTRA="--set k=v ..." adds train_stage1 overrides; FMDPO=0 skips FM-DPO.
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
t0=$(date +%s)
source "$ROOT/scripts/gpu_env.sh"
OUTD="${OUT:-/tmp/gpu_pair_out}"
mkdir -p "$OUTD"
DEADLINE="${DEADLINE_S:-560}"
SCENES="${SCENES:-40000}"
TRAIN_S="${TRAIN_S:-850}"
BATCH="${BATCH:-256}"
VARIANTS="${VARIANTS:-cpu:configs/miniature_cpu wide:configs/miniature_wide}"
VAE="${VAE_FROM:-runs/ss_vae_cpu}/weights"
RANKS="${RANKS:-1}"
STEPS="${STEPS:-}"
INIT="${INIT:-}"
CACHE_SEED="${CACHE_SEED:-0}"
read -r -a EXTRA_ARGS <<<"${EXTRA:-}"
STATE="$ROOT/${STATE_DIR:-runs/gpu_pair}"
BUILD="$STATE/build"
LOG="$OUTD/call.log"
mkdir -p "$STATE"
elapsed() { echo $(( $(date +%s) - t0 )); }
say() { echo "[gpu $(elapsed) s] $*" | tee -a "$LOG"; }
say "start; state: $(ls "$STATE" | tr '\n' ' ')"
[ -f "$VAE/ss_encoder.safetensors" ] || { say "no $VAE/ss_encoder.safetensors: carry runs/ss_vae_cpu/weights"; exit 1; }

# 1. Build (once per machine).
if [ ! -x "$BUILD/train_stage1" ] || [ ! -x "$BUILD/train_fmdpo" ]; then
  gpu_configure "$BUILD" "$OUTD/configure.log" -DSIMU_BUILD_TESTS=OFF -DSIMU_BUILD_PYTHON=OFF -DSIMU_CUDA_KERNELS=OFF || exit 1
  ninja -C "$BUILD" build_stage1_data train_stage1 bench_train_stage1 train_fmdpo >"$OUTD/build.log" 2>&1 ||
    { grep -B2 -A8 -E "error|FAILED" "$OUTD/build.log" | head -60; exit 1; }
  say "built on $(nproc) cores"
fi
nvidia-smi --query-gpu=index,name,memory.total --format=csv,noheader | tee -a "$LOG"

# 2. The cache on the CPUs; benches and FM-DPO on the GPUs meanwhile.
cache_pid=""
if [ ! -f "$STATE/stage1.h5" ]; then
  "$BUILD/build_stage1_data" --out "$STATE/stage1.tmp.h5" --train "$SCENES" --val 300 --test 0 --seed "$CACHE_SEED" \
    --preprocess configs/miniature_cpu/preprocess.yaml --resolution 16 --threads "$(( $(nproc) - 4 ))" \
    >"$STATE/cache.log" 2>&1 && mv "$STATE/stage1.tmp.h5" "$STATE/stage1.h5" &
  cache_pid=$!
fi
i=0
bench_pids=()
for v in $VARIANTS; do
  name="${v%%:*}"; cfg="${v#*:}"
  [ -n "$STEPS" ] && [ ! -f "$STATE/steps_$name" ] && echo "$STEPS" >"$STATE/steps_$name"
  if [ ! -f "$STATE/steps_$name" ]; then
    (CUDA_VISIBLE_DEVICES=$i "$BUILD/bench_train_stage1" --config "$cfg/train_stage1.yaml" --device cuda --precision bf16 \
       --batch "$BATCH" --steps 20 --warmup 5 --resolution 16 >"$STATE/bench_$name.txt" 2>&1
     rate=$(awk -F'|' '/^\| cuda/ {gsub(/ /, "", $8); print $8}' "$STATE/bench_$name.txt" | tail -n 1)
     # The real step also encodes the targets and reads the cache: 1.07x the benchmark's at this size (docs/miniature.md).
     python3 -c "print(max(100, int($TRAIN_S * float('$rate') / $BATCH / ${STEP_FACTOR:-1.15})))" >"$STATE/steps_$name"
     say "bench $name: $rate samples/s -> train.steps $(cat "$STATE/steps_$name") for $TRAIN_S s") &
    bench_pids+=($!)
  fi
  i=$(( i + 1 ))
done
for p in "${bench_pids[@]}"; do wait "$p"; done
fmdpo() {  # name, ranks, extra args
  local name="$1" n="$2"; shift 2
  [ -d "$STATE/$name/adapter" ] && return 0
  "$BUILD/train_fmdpo" --config configs/miniature_cpu/lora.yaml --set objective.beta=50.0 --set train.device=cuda \
    --set train.precision=bf16 --set data.micro_batch=8 --set data.cache=data/pairs_cpu.h5 --set run.out_dir="$STATE/$name" \
    --set run.progress=false --set run.checkpoint_every=0 --overwrite "$@" >"$STATE/$name.log" 2>&1 ||
    { say "$name failed: $(tail -n 3 "$STATE/$name.log")"; return 0; }
  say "$name ($n rank(s)): $(tail -n 1 "$STATE/$name/metrics.jsonl" | cut -c1-240)"
}
if [ -f data/pairs_cpu.h5 ] && [ "${FMDPO:-1}" != 0 ]; then
  CUDA_VISIBLE_DEVICES=0 fmdpo fmdpo_r1 1
  CUDA_VISIBLE_DEVICES=0,1 fmdpo fmdpo_r2 2 --nproc-per-node 2
fi
if [ -n "$cache_pid" ]; then
  wait "$cache_pid"
  [ -f "$STATE/stage1.h5" ] || { say "cache failed: $(tail -n 5 "$STATE/cache.log")"; exit 1; }
  say "cache: $(tail -n 1 "$STATE/cache.log")"
fi

# 3. The variants in parallel until this call's deadline (packing takes ~30 s).
left=$(( DEADLINE - $(elapsed) - 45 ))
i=0
pids=()
for v in $VARIANTS; do
  name="${v%%:*}"; cfg="${v#*:}"
  run="$STATE/stage1_$name"
  if [ ! -d "$run/model" ] && [ "$left" -gt 30 ]; then
    resume=(); [ -d "$run/checkpoints" ] && resume=(--resume latest)
    gpus=$i; ranks=(); init=()
    [ "$RANKS" -gt 1 ] && { gpus=$(seq -s, 0 $(( RANKS - 1 ))); ranks=(--nproc-per-node "$RANKS"); }
    [ -n "$INIT" ] && init=(--set "model.init=$INIT")
    CUDA_VISIBLE_DEVICES=$gpus "$BUILD/train_stage1" --config "$cfg/train_stage1.yaml" "${resume[@]}" "${ranks[@]}" "${init[@]}" \
      --set train.device=cuda --set train.precision=bf16 --set "data.global_batch=$(( BATCH * RANKS ))" --set "data.micro_batch=$BATCH" \
      --set "train.steps=$(cat "$STATE/steps_$name")" --set data.cache="$STATE/stage1.h5" --set run.out_dir="$run" \
      --set "targets.encoder_config=$VAE/ss_encoder.json" --set "targets.encoder_weights=$VAE/ss_encoder.safetensors" \
      --set run.checkpoint_every=1000 --set "run.stop_after_s=$left" --set run.log_every=100 --set run.progress=false "${EXTRA_ARGS[@]}" \
      >>"$STATE/stage1_$name.log" 2>&1 &
    pids+=($!)
  fi
  i=$(( i + 1 ))
done
for p in "${pids[@]}"; do wait "$p"; done
for v in $VARIANTS; do
  name="${v%%:*}"; cfg="${v#*:}"
  run="$STATE/stage1_$name"
  say "stage1 $name: $(tail -n 1 "$run/metrics.jsonl" 2>/dev/null | cut -c1-300)"
done

# 4. What comes back: one archive in parts of <= 15 MB.
cd "$STATE"
have=()
for f in steps_* bench_*.txt cache.log stage1_*.log stage1_*/metrics.jsonl stage1_*/model fmdpo_r*.log \
         fmdpo_r*/metrics.jsonl fmdpo_r*/adapter fmdpo_r*/*.yaml fmdpo_r*/*.json; do
  [ -e "$f" ] && have+=("$f")
done
tar czf /tmp/pair_back.tgz "${have[@]}" && split -b 15M -d /tmp/pair_back.tgz "$OUTD/pair_back.tgz.part"
say "packed: $(du -sh /tmp/pair_back.tgz | cut -f1) (${#have[@]} items)"
