#!/usr/bin/env bash
# The paper's FM-DPO experiment on the shipped CPU miniature (issue 36, docs/miniature.md "FM-DPO on the
# miniature"), from nothing, on this machine's CPU (~15 min on 2 cores):
#   1. preference pairs of the world's TRAIN split: world pairs (1,000 occlusion-completion + 1,000
#      clean-preservation candidates), then build_pairs --filter-gt (the paper's filter: x+ must be
#      closer to the ground truth than x-; the report counts the drops);
#   2. train_fmdpo --config configs/miniature_cpu/lora.yaml with SEEDS (train.seed = data.seed);
#   3. eval_lift on the TEST split and the held-out family (never in pairs), base and base + adapter on
#      the same objects and noise (--compare-adapter, 95% bootstrap intervals of the deltas), with the
#      amodal crop (the resampling input the pairs are made for), per visibility range: all objects
#      of test scenes (mostly unoccluded), 40-70% and 20-40% visible (scenes with one such target).
#   bash scripts/fmdpo_miniature.sh            # BUILD_DIR (build/), SEEDS ("0 1"), COUNT (500), OUT_RUNS (runs/)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
BUILD="${BUILD_DIR:-$ROOT/build}"
RUNS="${OUT_RUNS:-$ROOT/runs}"
SEEDS="${SEEDS:-0 1}"
COUNT="${COUNT:-500}"
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-2}"
set -x
mkdir -p data "$RUNS"
# 1. Pairs (train split, scene seeds from 0; point maps corrupted as the stage-1 cache's).
"$BUILD/world" pairs --completion 1000 --preservation 1000 --seed 0 --resolution 16 --out data/pairs_cpu --threads 2 --overwrite
"$BUILD/build_pairs" --manifest data/pairs_cpu/manifest.jsonl --out data/pairs_cpu.h5 --overwrite --device cpu \
  --filter-gt --report data/pairs_cpu.report.json --batch 32 --seed 0
# 2. FM-DPO, one run per seed.
for s in $SEEDS; do
  "$BUILD/train_fmdpo" --config configs/miniature_cpu/lora.yaml --set "train.seed=$s" --set "data.seed=$s" \
    --set "run.out_dir=$RUNS/fmdpo_cpu_s$s" --overwrite
done
# 3. Evaluation: base vs base + adapter, same objects and noise (eval seed 0), amodal crop.
for s in $SEEDS; do
  A="$RUNS/fmdpo_cpu_s$s/adapter"
  common=(--seed 0 --depth clean --amodal-crop --device cpu --no-pictures --compare-adapter "$A" --overwrite
          --samples 1 --select first)  # one sample per object, as the documented tables were made
  "$BUILD/eval_lift" --world test --count "$COUNT" "${common[@]}" --out "$RUNS/eval_fmdpo_s${s}_all"
  "$BUILD/eval_lift" --world test --visible 40-70 --count "$COUNT" "${common[@]}" --out "$RUNS/eval_fmdpo_s${s}_40_70" \
    --set scene.targets=1 --set scene.visible_min=0.4 --set scene.visible_max=0.7
  "$BUILD/eval_lift" --world test --visible 20-40 --count "$COUNT" "${common[@]}" --out "$RUNS/eval_fmdpo_s${s}_20_40" \
    --set scene.targets=1 --set scene.visible_min=0.2 --set scene.visible_max=0.4
  "$BUILD/eval_lift" --world heldout --count $(( COUNT / 5 )) "${common[@]}" --out "$RUNS/eval_fmdpo_s${s}_heldout"
done
