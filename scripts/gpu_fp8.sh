#!/usr/bin/env bash
# The FP8 frozen base's device measurements (docs/training.md "FP8 frozen base"; figures in
# docs/benchmarks.md), after scripts/gpu_build_test.sh has built build-gpu/ (targets fp8_fidelity,
# bench_fmdpo, pairs, train_fmdpo). Tables go to $OUT (or ./bench-out). Each part takes a few
# minutes at most on one H100/H200:
#   bash scripts/gpu_fp8.sh fidelity   # fp8_fidelity at 2,800 (with fp32) and 7,528 tokens, two lora_B scales
#   bash scripts/gpu_fp8.sh speed      # bench_fmdpo --fp8-base off,on,all at 7,528 and 2,800, micro 4 (PEAK: TFLOP/s)
#   bash scripts/gpu_fp8.sh curves     # two 300-step runs (bf16 base, FP8 base) on one cache -> curves.csv
#                                      # (LAYERS=all: the FP8 run with train.fp8_base_layers all)
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
B="${BUILD_DIR:-$ROOT/build-gpu}"
O="${OUT:-$ROOT/bench-out}"
mkdir -p "$O"
source "$ROOT/scripts/gpu_env.sh"  # .carry's libraries, SIMU_SHARED_DIR, NCCL settings
cd "$ROOT"
run() { local name="$1"; shift; echo "== $name: $*"; "$@" 2>&1 | tee "$O/$name.txt" | tail -30; }
case "${1:-}" in
  fidelity)
    run fp8_fidelity_c2800 "$B/fp8_fidelity" --cond-len 2800 --pairs 8 --micro 2 --fp32 --csv "$O/fp8_tensors_c2800.csv"
    run fp8_fidelity_c7528 "$B/fp8_fidelity" --cond-len 7528 --pairs 8 --micro 2
    run fp8_fidelity_c2800_b1e-2 "$B/fp8_fidelity" --cond-len 2800 --pairs 8 --micro 2 --lora-b-std 1e-2 ;;
  speed)
    run fmdpo_fp8 "$B/bench_fmdpo" --micro "${MICRO:-4}" --fp8-base off,on,all --peak-tflops "${PEAK:-989.4}" ;;
  curves)
    W="${WORK:-/tmp/fp8_curves}"
    mkdir -p "$W" "$O/fp8_curves"
    "$B/pairs" make --out "$W/pairs.h5" --n 64 --cond-len 2800 --cond-len-min 2800 --seed 0 --overwrite || exit 1
    for base in bf16 fp8; do
      flag=false; [ "$base" = fp8 ] && flag=true
      run "fp8_curves_$base" "$B/train_fmdpo" --config configs/fp8_curves.yaml --overwrite --set data.cache="$W/pairs.h5" \
        --set train.fp8_base=$flag --set train.fp8_base_layers="${LAYERS:-adapted}" --set run.out_dir="$W/$base"
      cp "$W/$base/metrics.jsonl" "$O/fp8_curves/$base.jsonl"
    done
    run fp8_curves_summary python3 scripts/fp8_curves.py --bf16 "$O/fp8_curves/bf16.jsonl" --fp8 "$O/fp8_curves/fp8.jsonl" \
      --csv "$O/fp8_curves/curves.csv" --png "$O/fp8_curves/curves.png" ;;
  *) echo "usage: bash scripts/gpu_fp8.sh fidelity|speed|curves" >&2; exit 2 ;;
esac
exit 0
