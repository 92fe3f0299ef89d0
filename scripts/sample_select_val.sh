#!/usr/bin/env bash
# The validation runs of docs/rules/sample_select.md (CPU, the shipped miniature): best of K samples by the
# render-and-compare score against the point map (eval_lift --samples K --select render-compare) paired
# with the shipped one-sample lift, on val seeds 16-23 (200 objects no earlier rule used).
#   bash scripts/sample_select_val.sh run     # K = 1, 4 (the candidate) and 8 (report only); two jobs at once
#   bash scripts/sample_select_val.sh table   # the paired tables (scripts/merge_eval_shards.py)
# Every run: eval_lift --world val --count 25 --seed S --depth clean --align simuscene, one thread.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
BUILD="${BUILD_DIR:-$ROOT/build}"
RUNS="${RUNS:-runs/eval_select}"
PY="${SIMU_PYTHON:-$ROOT/.deps/venv/bin/python}"
SEEDS="16 17 18 19 20 21 22 23"
mkdir -p "$RUNS"
ev() {  # out seed [extra]
  local out="$1" seed="$2"; shift 2
  [ -f "$RUNS/$out/summary.json" ] && return 0
  OMP_NUM_THREADS=1 "$BUILD/eval_lift" --world val --count 25 --seed "$seed" --depth clean --align simuscene \
    --threads 1 --no-pictures --out "$RUNS/$out" "$@" >"$RUNS/$out.log" 2>&1
}
case "${1:-}" in
  run)
    for s in $SEEDS; do
      ev "k1_$s" "$s" &
      ev "k4_$s" "$s" --samples 4 --select render-compare &
      wait
    done
    for s in $SEEDS; do ev "k8_$s" "$s" --samples 8 --select render-compare & [ $((s % 2)) -eq 1 ] && wait; done
    wait ;;
  table)
    "$PY" scripts/merge_eval_shards.py --model k1 "$RUNS/k1_*/summary.json" --model k4 "$RUNS/k4_*/summary.json" \
      --compare k1 k4
    "$PY" scripts/merge_eval_shards.py --model k1 "$RUNS/k1_*/summary.json" --model k8 "$RUNS/k8_*/summary.json" \
      --compare k1 k8 ;;
  *) sed -n '2,7p' "$0" | sed 's/^# \{0,1\}//'; exit 2 ;;
esac
