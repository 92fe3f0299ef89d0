#!/usr/bin/env bash
# Builds the miniature (weights/miniature_cpu layout) from nothing in one process: the commands and seeds,
# in order (docs/miniature.md). Needs a build (./run demo or cmake) in $BUILD_DIR (default build/).
#   bash scripts/make_miniature.sh                 # the first version, on this machine's CPU (~10 + 7 + 60 min
#                                                  # on 2 cores): 25,000 cache scenes, 4,000 steps of 64
#   DEVICE=cuda bash scripts/make_miniature.sh     # on a GPU (bf16) with the shipped Stage 1's recipe: 40,000
#                                                  # cache scenes, 5,600 steps of 256 (the shipped weights were
#                                                  # made in resumed device calls: scripts/make_miniature_gpu.sh)
# Environment: VAE_STEPS (1500), SCENES, STAGE1_STEPS, BATCH (as above per device), THREADS (2),
# EVAL_COUNT (200 test objects), OUT_RUNS (runs/).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
BUILD="${BUILD_DIR:-$ROOT/build}"
DEVICE="${DEVICE:-cpu}"
RUNS="${OUT_RUNS:-$ROOT/runs}"
THREADS="${THREADS:-2}"
if [ "$DEVICE" = cpu ]; then PREC=fp32; BATCH="${BATCH:-64}"; STAGE1_STEPS="${STAGE1_STEPS:-4000}"; SCENES="${SCENES:-25000}"
else PREC=bf16; BATCH="${BATCH:-256}"; STAGE1_STEPS="${STAGE1_STEPS:-5600}"; SCENES="${SCENES:-40000}"; fi
set -x
# 1. The sparse-structure VAE on fresh world shapes of the train split (seed 0); eval.json has the test IoU.
"$BUILD/train_ss_vae" --config configs/miniature_cpu/ss_vae.yaml --set "train.steps=${VAE_STEPS:-1500}" \
  --set train.device="$DEVICE" --set train.precision="$PREC" --set eval.every=500 --set run.out_dir="$RUNS/ss_vae_cpu"
# 2. The stage-1 cache: world scenes of the train / val splits (scene seeds from 0), corrupted point maps.
mkdir -p data
"$BUILD/build_stage1_data" --out data/stage1_cpu.h5 --train "$SCENES" --val 500 --test 0 \
  --preprocess configs/miniature_cpu/preprocess.yaml --resolution 16 --threads "$THREADS"
# 3. Stage-1 pretraining with the frozen encoder's latents as targets (train.seed 0, data.seed 0).
"$BUILD/train_stage1" --config configs/miniature_cpu/train_stage1.yaml --set "train.steps=$STAGE1_STEPS" \
  --set train.device="$DEVICE" --set train.precision="$PREC" --set "data.global_batch=$BATCH" --set "data.micro_batch=$BATCH" \
  --set targets.encoder_config="$RUNS/ss_vae_cpu/weights/ss_encoder.json" \
  --set targets.encoder_weights="$RUNS/ss_vae_cpu/weights/ss_encoder.safetensors" --set run.out_dir="$RUNS/stage1_cpu"
# 4. The folder: fp16 weights, configs, manifest (commit, commands, seeds).
"${PYTHON:-$ROOT/.deps/venv/bin/python}" scripts/ship_miniature.py --vae "$RUNS/ss_vae_cpu" --stage1 "$RUNS/stage1_cpu" \
  --out weights/miniature_cpu
# 5. The evaluation on the world's test split and the held-out family (the table in the manifest).
for split in test heldout; do
  "$BUILD/eval_lift" --world "$split" --count "${EVAL_COUNT:-200}" --seed 0 --device "$DEVICE" --no-pictures \
    --out "$RUNS/eval_$split" --overwrite
done
"${PYTHON:-$ROOT/.deps/venv/bin/python}" scripts/ship_miniature.py --out weights/miniature_cpu \
  --eval "$RUNS/eval_test/summary.json" --eval "$RUNS/eval_heldout/summary.json"
