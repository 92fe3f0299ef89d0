#!/usr/bin/env bash
# Runs every GPU benchmark of the toolkit on the device after scripts/gpu_build_test.sh has built
# build-gpu/, writing each table to $OUT (or ./bench-out). MFU and utilisation figures are ratios to
# the machine's own measured bf16 matrix-product rate (8192^3 through PyTorch, median of 10).
#   bash scripts/gpu_bench.sh [all|stage1|embedder|fmdpo|resample|lift|fmdpo2]
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
B="${BUILD_DIR:-$ROOT/build-gpu}"
O="${OUT:-$ROOT/bench-out}"
mkdir -p "$O"
source "$ROOT/scripts/gpu_env.sh"  # .carry's libraries, SIMU_SHARED_DIR, NCCL settings
what="${1:-all}"
peak="$(python3 - <<'PY'
import torch
a=torch.randn(8192,8192,device='cuda',dtype=torch.bfloat16); b=torch.randn(8192,8192,device='cuda',dtype=torch.bfloat16)
for _ in range(3): a@b
ts=[]
for _ in range(10):
    s=torch.cuda.Event(enable_timing=True); e=torch.cuda.Event(enable_timing=True); s.record(); a@b; e.record(); torch.cuda.synchronize(); ts.append(s.elapsed_time(e))
ts.sort(); print("%.1f" % (2*8192**3/ts[5]/1e9))
PY
)"
echo "measured bf16 matmul rate: $peak TFLOP/s" | tee "$O/peak.txt"
run() { local name="$1"; shift; echo "== $name: $*"; "$@" 2>&1 | tee "$O/$name.txt" | tail -25; }
case "$what" in all|stage1) run stage1 "$B/bench_stage1";; esac
case "$what" in all|embedder) run embedder "$B/bench_embedder" --batch 1 8;; esac
case "$what" in all|resample) run resample "$B/bench_resample" --batches 1 8;; esac
case "$what" in all|lift) run lift "$B/bench_lift" --batches 1 8;; esac
# FM-DPO at the released embedder's 7,528 condition tokens (headline) and at 2,800 (COND_LENS overrides).
for L in ${COND_LENS:-7528 2800}; do
  case "$what" in all|fmdpo) run "fmdpo_c$L" "$B/bench_fmdpo" --micro "${MICRO:-1,2,4}" --peak-tflops "$peak" --cond-len "$L" ${FMDPO_ARGS:-};; esac
  case "$what" in fmdpo2) run "fmdpo2_c$L" "$B/bench_fmdpo" --micro "${MICRO:-1,2,4}" --peak-tflops "$peak" --nproc-per-node 2 --cond-len "$L" ${FMDPO_ARGS:-};; esac
done
exit 0
