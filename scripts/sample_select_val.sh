#!/usr/bin/env bash
# The validation runs of docs/rules/sample_select.md (the shipped miniature, CPU): best of K samples by the
# render-and-compare score against the point map (eval_lift --samples K --select render-compare), paired
# with the shipped one-sample lift, on val seeds 16-23 (200 objects no earlier rule used).
#   bash scripts/sample_select_val.sh jobs    # writes runs/select_val_jobs.txt: K = 1, 4 (the candidate), 8
#                                             # (report only) with --align simuscene; K = 1, 4 with --align icp
#   device run (carry .carry/prefix/usr/{include,lib/x86_64-linux-gnu,lib/libgloo.so,share,src} and the jobs file):
#     JOBS_FILE=runs/select_val_jobs.txt bash scripts/gpu_eval_shards.sh    (here: EVAL_BUILD=build PARALLEL=2 OUT=DIR)
#   RUNS=DIR bash scripts/sample_select_val.sh table   # the paired tables (scripts/merge_eval_shards.py)
# After the decision (docs/miniature.md), the test split and the held-out family, and the shipped adapter
# at 40-70% visible with the best of 4 (docs/results.md), the same way (device: gpu_eval_shards.sh):
#   bash scripts/sample_select_val.sh test      # runs/select_test_jobs_a.txt (one sample / best of 4, --align
#                                               # simuscene) and _b.txt (best of 4, --align icp)
#   bash scripts/sample_select_val.sh adapter   # runs/adapter_k4_jobs.txt (32 shards, base vs the adapter)
#   RUNS=DIR bash scripts/sample_select_val.sh test_table | adapter_table
# Every job: eval_lift --world val --count 25 --seed S --depth clean, one thread; the model folder's files
# with its surface offset (0.5) given explicitly.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
RUNS="${RUNS:-runs/eval_select}"
PY="${SIMU_PYTHON:-$ROOT/.deps/venv/bin/python}"
SEEDS="16 17 18 19 20 21 22 23"
shard_jobs() {  # FILE NAME N ARGS...: N job lines "NAME_i weights/miniature_cpu ARGS --shard i/N" appended to FILE
  local file="$1" name="$2" n="$3"; shift 3
  for i in $(seq 0 $((n - 1))); do echo "${name}_$i weights/miniature_cpu $* --shard $i/$n" >>"$file"; done
}
case "${1:-}" in
  jobs)
    mkdir -p runs
    : >runs/select_val_jobs.txt
    for s in $SEEDS; do
      base="--world val --count 25 --seed $s --depth clean --surface-offset 0.5"
      for k in 8 4 1; do
        sel=""; [ "$k" -gt 1 ] && sel=" --samples $k --select render-compare"
        # (no trailing blank: xargs -L joins a line that ends in one with the next)
        echo "k${k}_$s weights/miniature_cpu $base --align simuscene$sel" >>runs/select_val_jobs.txt
      done
    done
    for s in $SEEDS; do
      base="--world val --count 25 --seed $s --depth clean --surface-offset 0.5"
      echo "icp_k1_$s weights/miniature_cpu $base --align icp" >>runs/select_val_jobs.txt
      echo "icp_k4_$s weights/miniature_cpu $base --align icp --samples 4 --select render-compare" >>runs/select_val_jobs.txt
    done
    wc -l runs/select_val_jobs.txt ;;
  test)
    : >runs/select_test_jobs_a.txt
    : >runs/select_test_jobs_b.txt
    one="--samples 1 --select first" four="--samples 4 --select render-compare"
    test="--world test --count 500 --seed 0 --depth both --surface-offset 0.5"
    held="--world heldout --count 100 --seed 0 --depth both --surface-offset 0.5"
    for k in 4 1; do
      sel="$four"; [ "$k" -eq 1 ] && sel="$one"
      shard_jobs runs/select_test_jobs_a.txt "t_k$k" 20 $test --align simuscene $sel
      shard_jobs runs/select_test_jobs_a.txt "h_k$k" 4 $held --align simuscene $sel
    done
    shard_jobs runs/select_test_jobs_b.txt t_icpk4 20 $test --align icp $four
    shard_jobs runs/select_test_jobs_b.txt h_icpk4 4 $held --align icp $four
    wc -l runs/select_test_jobs_a.txt runs/select_test_jobs_b.txt ;;
  test_table)
    for w in t h; do
      "$PY" scripts/merge_eval_shards.py --model k1 "$RUNS/${w}_k1_*/summary.json" --model k4 "$RUNS/${w}_k4_*/summary.json" \
        --model icp_k4 "$RUNS/${w}_icpk4_*/summary.json" --compare k1 k4
      "$PY" scripts/merge_eval_shards.py --model k1 "$RUNS/${w}_k1_*/summary.json" --model icp_k4 "$RUNS/${w}_icpk4_*/summary.json" \
        --compare k1 icp_k4 | sed -n '/paired by object/,$p'
    done ;;
  adapter)
    : >runs/adapter_k4_jobs.txt
    shard_jobs runs/adapter_k4_jobs.txt a4070_k4 32 --world test --count 500 --seed 0 --depth clean --amodal-crop \
      --visible 40-70 --set scene.targets=1 --set scene.visible_min=0.4 --set scene.visible_max=0.7 --align simuscene \
      --surface-offset 0.5 --compare-adapter weights/miniature_cpu/adapter
    wc -l runs/adapter_k4_jobs.txt ;;
  adapter_table)
    "$PY" scripts/merge_eval_shards.py --model base "$RUNS/a4070_k4_*/summary.json" \
      --model tuned "$RUNS/a4070_k4_*/summary.json@compare" --compare base tuned ;;
  table)
    for pair in "k1 k4" "k1 k8" "icp_k1 icp_k4" "k1 icp_k4"; do
      set -- $pair
      echo "== $1 -> $2"
      "$PY" scripts/merge_eval_shards.py --model "$1" "$RUNS/$1_[0-9]*/summary.json" --model "$2" "$RUNS/$2_[0-9]*/summary.json" \
        --compare "$1" "$2"
    done ;;
  *) sed -n '2,18p' "$0" | sed 's/^# \{0,1\}//'; exit 2 ;;
esac
