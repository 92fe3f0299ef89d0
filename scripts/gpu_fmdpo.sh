#!/usr/bin/env bash
# FM-DPO on the shipped miniature, on one GPU (issue 36, docs/results.md): the paper's recipe in bf16 on
# CUDA over three seeds, and its ablations (beta, LoRA rank, pair kinds, steps / learning rate) over
# two seeds, each adapter then evaluated against the base model on the test split. Device calls of at
# most ~10 minutes continue each other while the machine stays warm: every stage is skipped when its
# output is already in $STATE, and each call stops before its deadline.
#   1. configure and build train_fmdpo and eval_lift (skipped when built);
#   2. train_fmdpo --config configs/miniature_cpu/lora.yaml --set train.device=cuda --set
#      train.precision=bf16, one run per (variant, seed), JOBS at a time on the one GPU;
#   3. eval_lift --world test --visible 40-70 --count N --seed 0 --amodal-crop --align simuscene
#      --compare-adapter <run>/adapter (the same objects and noise for every adapter), and the
#      all-objects run (mostly unoccluded: the preservation check), for the runs EVALS_40_70 and
#      EVALS_ALL name, in parallel;
#   4. pack what comes back into $OUT: every run's metrics.jsonl and adapter, every summary.json.
#   Adapters already in $STATE/runs (carried from an earlier call's pack) are not trained again.
#   Environment: TRAIN_RUNS ("variant:seed ..."), EVALS_40_70 / EVALS_ALL ("run_sS:count ..."),
#   EVAL_WORLD (test | val: val is the split for choosing among variants), EVAL_JOBS, JOBS, COUNT.
#   device run (carry .carry/prefix/usr/{include,lib/x86_64-linux-gnu,lib/libgloo.so,share,src}, i.e.
#   without lib/coacd, to stay under 64 MiB; data/pairs_cpu.h5, made by scripts/fmdpo_miniature.sh;
#   runs/gpu_fmdpo/runs to reuse adapters). The 2026-11-29 calls, in order (docs/results.md):
#     DEADLINE_S=570 bash scripts/gpu_fmdpo.sh      # build, 17 runs; its first 500-object eval ran out
#     EVALS_40_70="recipe_s0:200 ... lr1e-4_steps3000_s1:200" EVALS_ALL="" EVAL_JOBS=17 \
#       DEADLINE_S=585 bash scripts/gpu_fmdpo.sh    # the ablation table (test, 200 objects each)
#     TRAIN_RUNS="beta5:0 beta5:1 beta20:0 beta20:1" EVAL_WORLD=val \
#       EVALS_40_70="recipe_s0:200 recipe_s1:200 beta5_s0:200 ... beta50_s1:200" EVALS_ALL="" EVAL_JOBS=8 \
#       DEADLINE_S=500 bash scripts/gpu_fmdpo.sh    # the beta choice on val
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
t0=$(date +%s)
source "$ROOT/scripts/gpu_env.sh"
OUTD="${OUT:-/tmp/gpu_fmdpo_out}"
mkdir -p "$OUTD"
DEADLINE="${DEADLINE_S:-560}"
COUNT="${COUNT:-500}"
JOBS="${JOBS:-4}"
STATE="$ROOT/runs/gpu_fmdpo"
BUILD="$STATE/build"
LOG="$OUTD/call.log"
mkdir -p "$STATE"
elapsed() { echo $(( $(date +%s) - t0 )); }
say() { echo "[gpu $(elapsed) s] $*" | tee -a "$LOG"; }
left() { echo $(( DEADLINE - $(elapsed) )); }
say "start; state: $(ls "$STATE" | tr '\n' ' ')"
[ -f data/pairs_cpu.h5 ] || { say "data/pairs_cpu.h5 missing: carry it (scripts/fmdpo_miniature.sh makes it)"; exit 1; }

# 1. Build (once per machine).
if [ ! -x "$BUILD/train_fmdpo" ] || [ ! -x "$BUILD/eval_lift" ]; then
  gpu_configure "$BUILD" "$OUTD/configure.log" -DSIMU_BUILD_TESTS=OFF -DSIMU_BUILD_PYTHON=OFF -DSIMU_CUDA_KERNELS=OFF || exit 1
  ninja -C "$BUILD" train_fmdpo eval_lift >"$OUTD/build.log" 2>&1 ||
    { grep -B2 -A8 -E "error|FAILED" "$OUTD/build.log" | head -60; exit 1; }
  say "built on $(nproc) cores"
fi
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee -a "$LOG"

# 2. The runs: name and --set overrides. The recipe (configs/miniature_cpu/lora.yaml: beta 500, r 8 /
#    alpha 16, both pair kinds at weights 1.0 / 0.1, lr 1e-5, 1,500 steps) and one change per ablation.
declare -A VARIANT=(
  [recipe]=""
  [beta5]="objective.beta=5.0"
  [beta20]="objective.beta=20.0"
  [beta50]="objective.beta=50.0"
  [beta150]="objective.beta=150.0"
  [beta5000]="objective.beta=5000.0"
  [rank4]="lora.r=4 lora.alpha=8"
  [rank32]="lora.r=32 lora.alpha=64"
  [completion_only]="objective.weight_preservation=0.0"
  [preservation_only]="objective.weight_completion=0.0"
  [lr1e-4_steps3000]="optim.lr=1.0e-4 train.steps=3000"
)
# TRAIN_RUNS: "variant:seed" items (default: the recipe over seeds 0-2, each ablation over seeds 0-1).
if [ -n "${TRAIN_RUNS:-}" ]; then
  read -r -a RUNS <<<"$TRAIN_RUNS"
else
  RUNS=()
  for s in 0 1 2; do RUNS+=("recipe:$s"); done
  for v in beta50 beta5000 rank4 rank32 completion_only preservation_only lr1e-4_steps3000; do
    for s in 0 1; do RUNS+=("$v:$s"); done
  done
fi
train_one() {
  local v="${1%%:*}" s="${1##*:}" dir="$STATE/runs/${1%%:*}_s${1##*:}"
  [ -f "$dir/adapter/adapter_model.safetensors" ] && return 0
  local sets=(--set train.device=cuda --set train.precision=bf16 --set "train.seed=$s" --set "data.seed=$s"
              --set "run.out_dir=$dir" --set run.log_every=10)
  for kv in ${VARIANT[$v]}; do sets+=(--set "$kv"); done
  "$BUILD/train_fmdpo" --config configs/miniature_cpu/lora.yaml "${sets[@]}" --overwrite >"$dir.log" 2>&1 ||
    echo "train $1 failed: $(tail -3 "$dir.log")"
}
mkdir -p "$STATE/runs"
pending=()
for r in "${RUNS[@]}"; do
  [ -f "$STATE/runs/${r%%:*}_s${r##*:}/adapter/adapter_model.safetensors" ] || pending+=("$r")
done
if [ "${#pending[@]}" -gt 0 ]; then
  say "training ${#pending[@]} run(s), $JOBS at a time"
  i=0
  while [ "$i" -lt "${#pending[@]}" ] && [ "$(left)" -gt 120 ]; do
    for j in $(seq 1 "$JOBS"); do
      [ "$i" -lt "${#pending[@]}" ] || break
      train_one "${pending[$i]}" &
      i=$(( i + 1 ))
    done
    wait
  done
  say "trained: $(ls "$STATE"/runs/*/adapter/adapter_model.safetensors 2>/dev/null | wc -l) adapters"
fi

# 3. Evaluations, EVAL_JOBS at a time (one metric thread each: the alignment and metrics are
#    single-threaded per object, and one process's scene-by-scene loop leaves most cores idle), each
#    stopped at the call's deadline. EVALS_40_70 / EVALS_ALL: "run:count" items.
EVAL_JOBS="${EVAL_JOBS:-14}"
EVALS_40_70="${EVALS_40_70:-recipe_s0:$COUNT recipe_s1:$COUNT recipe_s2:$COUNT}"
EVALS_ALL="${EVALS_ALL-recipe_s0:$COUNT}"
SPLIT="${EVAL_WORLD:-test}"   # val: the split for choosing among variants; test: the reported tables
SUFFIX=$([ "$SPLIT" = test ] && echo "" || echo "_$SPLIT")
mkdir -p "$STATE/eval"
eval_one() {  # run rows count
  local run="$1" rows="$2" n="$3" out="$STATE/eval/$1_$2$SUFFIX"
  local common=(--world "$SPLIT" --count "$n" --seed 0 --depth clean --amodal-crop --align simuscene --no-pictures
                --threads 1 --compare-adapter "$STATE/runs/$run/adapter" --overwrite --out "$out"
                --samples 1 --select first)  # one sample per object, as the documented tables were made
  if [ "$rows" = "40_70" ]; then
    common+=(--visible 40-70 --set scene.targets=1 --set scene.visible_min=0.4 --set scene.visible_max=0.7)
  fi
  OMP_NUM_THREADS=1 timeout "$(( $(left) - 30 ))" "$BUILD/eval_lift" "${common[@]}" >"$out.log" 2>&1 ||
    { say "eval $run $rows stopped: $(tail -c 200 "$out.log" | tr '\n' ' ')"; return; }
  say "eval $run $rows: $(python3 -c "
import json
d=json.load(open('$out/summary.json'))['deltas']['clean']
b='40-70%' if '$rows'=='40_70' else 'unoccluded'
for k in ('iou_mean','shape_iou_mean'):
  x=d[b][k]; print(f'{k} {x[\"base\"]:.4f} -> {x[\"compare\"]:.4f} ({x[\"delta\"]:+.4f} [{x[\"ci95\"][0]:+.4f}, {x[\"ci95\"][1]:+.4f}])', end='; ')
" 2>&1)"
}
jobs_run=0
for item in $(for e in $EVALS_40_70; do echo "$e:40_70"; done) $(for e in $EVALS_ALL; do echo "$e:all"; done); do
  IFS=: read -r run n rows <<<"$item"
  [ -f "$STATE/eval/${run}_${rows}$SUFFIX/summary.json" ] && continue
  [ -f "$STATE/runs/$run/adapter/adapter_model.safetensors" ] || { say "no adapter for $run"; continue; }
  [ "$(left)" -gt 90 ] || { say "deadline: evaluations left for the next call"; break; }
  eval_one "$run" "$rows" "$n" &
  jobs_run=$(( jobs_run + 1 ))
  if [ "$jobs_run" -ge "$EVAL_JOBS" ]; then wait -n; jobs_run=$(( jobs_run - 1 )); fi
done
wait

# 4. Pack: metrics and adapters of every run, every evaluation summary (one archive, split under 15 MB).
tar -C "$STATE" -czf "$OUTD/fmdpo_gpu.tgz" --exclude='*/checkpoints' --exclude='*/tensorboard' runs eval 2>/dev/null
sz=$(stat -c %s "$OUTD/fmdpo_gpu.tgz")
if [ "$sz" -gt 15000000 ]; then
  split -b 15000000 -d "$OUTD/fmdpo_gpu.tgz" "$OUTD/fmdpo_gpu.tgz.part" && rm "$OUTD/fmdpo_gpu.tgz"
fi
say "packed $(ls "$OUTD" | tr '\n' ' ')"
