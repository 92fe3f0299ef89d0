#!/usr/bin/env bash
# FM-DPO of the shipped miniature on pairs whose x+ is the ground truth's encoder latent (build_pairs
# --preferred gt-latent), against the shipped adapter's pairs (x+ sampled from the edited image, the
# paper's), everything else equal: the same manifest (data/pairs_cpu/, train split), filter, recipe
# (configs/miniature_cpu/lora.yaml at beta 20, the adapter shipped when this ran) and seeds 0 and 1. docs/results.md,
# "x+ from the ground truth". On 2 CPU cores:
#   bash scripts/fmdpo_gt_pairs.sh pairs    # data/pairs_cpu_gt.h5 (~3 min)
#   bash scripts/fmdpo_gt_pairs.sh train    # runs/fmdpo_gt_beta20_s{0,1} (~3 min, both seeds at once)
#   bash scripts/fmdpo_gt_pairs.sh val      # the choice: val, 200 objects at 40-70% and the unoccluded
#                                           # objects of 200, both pair sources, seeds 0 and 1 (~25 min)
#   bash scripts/fmdpo_gt_pairs.sh test     # test, 500 objects at 40-70% and 500 of all, gt pairs (~25 min)
# Evaluations: eval_lift --amodal-crop --align simuscene --depth clean --seed 0 --compare-adapter, the
# same objects and noise for base and tuned; two at a time, one thread each.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BUILD="${BUILD_DIR:-$ROOT/build}"
cd "$ROOT"
stage="${1:-}"
export BUILD
occl=(--visible 40-70 --set scene.targets=1 --set scene.visible_min=0.4 --set scene.visible_max=0.7)
source "$ROOT/scripts/eval_adapter_lib.sh"   # ev OUT ADAPTER WORLD COUNT [args]; OCC
case "$stage" in
  pairs)
    OMP_NUM_THREADS=2 "$BUILD/build_pairs" --manifest data/pairs_cpu/manifest.jsonl --out data/pairs_cpu_gt.h5 --overwrite \
      --device cpu --filter-gt --report data/pairs_cpu_gt.report.json --batch 32 --seed 0 --preferred gt-latent ;;
  train)
    for s in 0 1; do
      OMP_NUM_THREADS=1 "$BUILD/train_fmdpo" --config configs/miniature_cpu/lora.yaml --set objective.beta=20.0 \
        --set data.cache=data/pairs_cpu_gt.h5 --set "train.seed=$s" --set "data.seed=$s" \
        --set "run.out_dir=runs/fmdpo_gt_beta20_s$s" --set run.progress=false --overwrite >"runs/fmdpo_gt_beta20_s$s.log" 2>&1 &
    done
    wait ;;
  val)
    mkdir -p runs/eval_gt
    jobs=()
    for src in gt v2; do
      for s in 0 1; do
        a="runs/fmdpo_${src}_beta20_s$s/adapter"
        jobs+=("runs/eval_gt/val_${src}_s${s}_40_70 $a val 200 ${occl[*]}")
        jobs+=("runs/eval_gt/val_${src}_s${s}_all $a val 200")
      done
    done
    printf '%s\n' "${jobs[@]}" | xargs -P 2 -L 1 bash -c 'ev "$@"' _ ;;
  test)
    mkdir -p runs/eval_gt
    jobs=()
    for s in 0 1; do
      a="runs/fmdpo_gt_beta20_s$s/adapter"
      jobs+=("runs/eval_gt/test_gt_s${s}_40_70 $a test 500 ${occl[*]}")
      jobs+=("runs/eval_gt/test_gt_s${s}_all $a test 500")
    done
    printf '%s\n' "${jobs[@]}" | xargs -P 2 -L 1 bash -c 'ev "$@"' _ ;;
  *) sed -n '2,14p' "$0" | sed 's/^# \{0,1\}//'; [ "$stage" = "-h" ] || [ "$stage" = "--help" ] ;;
esac
