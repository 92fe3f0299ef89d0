#!/usr/bin/env bash
# The validation runs of docs/rules/decoder32.md (CPU): the candidate model folder (runs/cand_dec32: the
# shipped miniature with the 32^3 decoder of scripts/gpu_decoder32.sh) against the shipped one.
#   bash scripts/decoder32_val.sh offset     # 1. candidate, val seeds 0-3, --surface-offset 0.25 / 0.5 / 0.75
#   OFFSET=X bash scripts/decoder32_val.sh compare   # 2. candidate at offset X and the shipped model, seeds 0-7
#   OFFSET=X bash scripts/decoder32_val.sh table     # the paired table (scripts/merge_eval_shards.py)
#   OFFSET=0.5 bash scripts/decoder32_val.sh second  # docs/rules/decoder32_followup.md: seeds 8-15, both
#                                                    # models with --shape-grid 16, and its table
# Every run: eval_lift --world val --count 25 --seed K --depth clean --align simuscene, one thread, one
# sample per object (--samples 1 --select first: as these runs were made, before eval_lift's best of 4).
# The same runs for another candidate folder (the fifth Stage 1 of docs/rules/stage1_v5.md), beside these:
#   CAND=runs/cand_v5 LABEL=v5 OFFSET=0.5 bash scripts/decoder32_val.sh compare | table
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
BUILD="${BUILD_DIR:-$ROOT/build}"
CAND="${CAND:-runs/cand_dec32}"
LABEL="${LABEL:-cand}"
RUNS="${RUNS:-runs/eval_dec32}"
PY="${SIMU_PYTHON:-$ROOT/.deps/venv/bin/python}"
mkdir -p "$RUNS"
ev() {  # out model_dir seed [extra]
  local out="$1" model="$2" seed="$3"; shift 3
  [ -f "$RUNS/$out/summary.json" ] && return 0
  SIMU_DEFAULT_MODEL="$model" OMP_NUM_THREADS=1 "$BUILD/eval_lift" --world val --count 25 --seed "$seed" --depth clean \
    --align simuscene --threads 1 --no-pictures --samples 1 --select first --out "$RUNS/$out" "$@" >"$RUNS/$out.log" 2>&1
}
case "${1:-}" in
  offset)
    for k in 0 1 2 3; do
      for o in 0.25 0.5 0.75; do ev "cand_o${o}_$k" "$CAND" "$k" --surface-offset "$o" & done
      wait
    done
    for o in 0.25 0.5 0.75; do
      "$PY" scripts/merge_eval_shards.py --model "offset $o" "$RUNS/cand_o${o}_[0-3]/summary.json" | grep "unoccluded"
    done ;;
  compare)
    : "${OFFSET:?set OFFSET to the offset chosen by the offset step}"
    for k in 0 1 2 3 4 5 6 7; do
      ev "shipped_$k" weights/miniature_cpu "$k" &
      ev "${LABEL}_o${OFFSET}_$k" "$CAND" "$k" --surface-offset "$OFFSET" &
      wait
    done ;;
  second)
    : "${OFFSET:?set OFFSET}"
    for k in 8 9 10 11 12 13 14 15; do
      ev "g16_shipped_$k" weights/miniature_cpu "$k" --shape-grid 16 &
      ev "g16_${LABEL}_o${OFFSET}_$k" "$CAND" "$k" --surface-offset "$OFFSET" --shape-grid 16 &
      wait
    done
    "$PY" scripts/merge_eval_shards.py --model shipped "$RUNS/g16_shipped_*/summary.json" \
      --model "$LABEL" "$RUNS/g16_${LABEL}_o${OFFSET}_*/summary.json" --compare shipped "$LABEL" ;;
  table)
    : "${OFFSET:?set OFFSET}"
    "$PY" scripts/merge_eval_shards.py --model shipped "$RUNS/shipped_[0-7]/summary.json" \
      --model "$LABEL" "$RUNS/${LABEL}_o${OFFSET}_[0-7]/summary.json" --compare shipped "$LABEL" ;;
  *) sed -n '2,8p' "$0" | sed 's/^# \{0,1\}//'; exit 2 ;;
esac
