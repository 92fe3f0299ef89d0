#!/usr/bin/env bash
# Rebuilds the shipped miniature (weights/miniature_cpu) as it was made on 2026-11-29: the CPU
# miniature's architecture and recipe (configs/miniature_cpu), its sparse-structure VAE trained on this
# machine's CPU, and Stage 1 trained on one H200 (docs/miniature.md, "Retrained on one H200"). Seeds:
# VAE 0; cache scene seeds from 0 (train and val splits only); train.seed 0, data.seed 0.
#   1. here (CPU, ~11 min): bash scripts/make_miniature_gpu.sh vae
#   2. on the GPU machine, two device calls while it stays warm (carry .carry/prefix/usr/{include,
#      lib/x86_64-linux-gnu,lib/libgloo.so,share,src} and runs/ss_vae_cpu/weights); the second call
#      resumes (--resume latest) and ships runs/gpu_mini16/miniature:
#        bash scripts/make_miniature_gpu.sh stage1      (DEADLINE_S=570, then again)
#      It builds, writes the stage-1 cache (build_stage1_data --train 25000 --val 300 --resolution 16 on
#      14 threads: 96,356 samples), measures the rate (bench_train_stage1: 1,771 samples/s at batch 128,
#      so train.steps = 5,292 for 900 s), and runs train_stage1 --config configs/miniature_cpu/train_stage1.yaml
#      --set train.device=cuda --set train.precision=bf16 --set data.global_batch=128 --set data.micro_batch=128
#      --set train.steps=5292 (AdamW 1e-3, 300 warm-up steps, cosine to 5e-5; 677,000 samples, 7.1 minutes).
#   3. here: bring runs/gpu_mini16 back, then
#        .deps/venv/bin/python scripts/ship_miniature.py --vae runs/ss_vae_cpu --stage1 runs/gpu_mini16/stage1 \
#          --out weights/miniature_cpu --commands scripts/make_miniature_gpu.sh
#      and the evaluations of docs/miniature.md (eval_lift --align simuscene, test 500 and held-out 100).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
BUILD="${BUILD_DIR:-$ROOT/build}"
case "${1:-}" in
  vae)
    "$BUILD/train_ss_vae" --config configs/miniature_cpu/ss_vae.yaml --set train.steps=1500 --set train.device=cpu \
      --set train.precision=fp32 --set eval.every=500 --set run.out_dir=runs/ss_vae_cpu ;;
  stage1)
    CONFIG_DIR=configs/miniature_cpu RESOLUTION=16 SCENES=25000 BATCH=128 TRAIN_S=900 VAE_FROM=runs/ss_vae_cpu \
      STATE_DIR=runs/gpu_mini16 EVAL_COUNT=0 DEADLINE_S="${DEADLINE_S:-570}" bash scripts/gpu_miniature.sh ;;
  *) sed -n '2,22p' "$0" | sed 's/^# \{0,1\}//'; exit 2 ;;
esac
