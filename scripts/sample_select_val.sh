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
    for k in 4 1; do
      sel=""; [ "$k" -gt 1 ] && sel=" --samples 4 --select render-compare"
      [ "$k" -eq 1 ] && sel=" --samples 1 --select first"
      for i in $(seq 0 19); do
        echo "t_k${k}_$i weights/miniature_cpu --world test --count 500 --seed 0 --depth both --align simuscene --surface-offset 0.5 --shard $i/20$sel" >>runs/select_test_jobs_a.txt
      done
      for i in 0 1 2 3; do
        echo "h_k${k}_$i weights/miniature_cpu --world heldout --count 100 --seed 0 --depth both --align simuscene --surface-offset 0.5 --shard $i/4$sel" >>runs/select_test_jobs_a.txt
      done
    done
    for i in $(seq 0 19); do
      echo "t_icpk4_$i weights/miniature_cpu --world test --count 500 --seed 0 --depth both --align icp --surface-offset 0.5 --shard $i/20 --samples 4 --select render-compare" >>runs/select_test_jobs_b.txt
    done
    for i in 0 1 2 3; do
      echo "h_icpk4_$i weights/miniature_cpu --world heldout --count 100 --seed 0 --depth both --align icp --surface-offset 0.5 --shard $i/4 --samples 4 --select render-compare" >>runs/select_test_jobs_b.txt
    done
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
    for i in $(seq 0 31); do
      echo "a4070_k4_$i weights/miniature_cpu --world test --count 500 --seed 0 --depth clean --amodal-crop --visible 40-70 --set scene.targets=1 --set scene.visible_min=0.4 --set scene.visible_max=0.7 --align simuscene --surface-offset 0.5 --compare-adapter weights/miniature_cpu/adapter --shard $i/32" >>runs/adapter_k4_jobs.txt
    done
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
