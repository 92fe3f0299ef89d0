#!/usr/bin/env bash
# The FM-DPO adapter of the shipped base retrained on 2026-11-29 evening (docs/results.md, "The adapter of
# the third base"; the rule in docs/rules/stage1_v3.md, written before any adapter was trained): pairs
# rebuilt with this base from the same rendered candidates, beta 50 carried over from the previous
# base's validation choice, seeds 0 and 1, the CPU recipe of configs/miniature_cpu/lora.yaml. On 2 CPU cores:
#   bash scripts/fmdpo_v3.sh pairs          # data/pairs_v3.h5 (+ .report.json; ~5 min)
#   bash scripts/fmdpo_v3.sh train [B]      # runs/fmdpo_v3_beta<B>_s{0,1} (B = 50 by default; ~5 min)
#   bash scripts/fmdpo_v3.sh val [B]        # runs/eval_v3/val_b<B>_s{0,1}_{40_70,all} (~8 min)
#   bash scripts/fmdpo_v3.sh table          # the rule's table from every val summary
#   bash scripts/fmdpo_v3.sh test B         # seeds 0 and 1 on test: 500 objects at 40-70%, 500 of all and
#                                           # 100 of the held-out family (runs/eval_v3/{test,heldout}_b<B>_s*; ~25 min)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BUILD="${BUILD_DIR:-$ROOT/build}"
PY="${SIMU_PYTHON:-$ROOT/.deps/venv/bin/python}"
cd "$ROOT"
export BUILD
B="${2:-50}"
T="${TAG:-v3}"   # TAG=v4: the same steps for the fourth base (data/pairs_v4.h5, runs/fmdpo_v4_*, runs/eval_v4)
E="${EVAL_DIR:-runs/eval_$T}"   # where val / test / table read and write (EVAL_DIR=runs/eval_v4d32: the v4 adapters
                                # evaluated again with the 32^3 decoder shipped on 2026-11-30)
source "$ROOT/scripts/eval_adapter_lib.sh"   # ev OUT ADAPTER WORLD COUNT [args]; OCC
mkdir -p "$E"
case "${1:-}" in
  pairs)
    # The rendered candidates of scripts/fmdpo_miniature.sh step 1 (world pairs --completion 1000
    # --preservation 1000 --seed 0 --resolution 16 --out data/pairs_cpu), sampled by the shipped base.
    [ -f data/pairs_cpu/manifest.jsonl ] || "$BUILD/world" pairs --completion 1000 --preservation 1000 --seed 0 \
      --resolution 16 --out data/pairs_cpu --threads 2 --overwrite
    OMP_NUM_THREADS=1 "$BUILD/build_pairs" --manifest data/pairs_cpu/manifest.jsonl --out data/pairs_$T.h5 --overwrite \
      --device cpu --filter-gt --report data/pairs_$T.report.json --batch 32 --seed 0 ;;
  train)
    for s in 0 1; do echo "$B $s $T"; done | xargs -P 2 -L 1 bash -c 'OMP_NUM_THREADS=1 "$0/train_fmdpo" \
      --config configs/miniature_cpu/lora.yaml --set data.cache=data/pairs_$3.h5 --set objective.beta=$1.0 \
      --set train.seed=$2 --set data.seed=$2 --set run.out_dir=runs/fmdpo_$3_beta$1_s$2 --set run.progress=false \
      --overwrite >runs/fmdpo_$3_beta$1_s$2.log 2>&1' "$BUILD" ;;
  val)
    for s in 0 1; do
      a="runs/fmdpo_${T}_beta${B}_s$s/adapter"
      echo "$E/val_b${B}_s${s}_40_70 $a val 200 $OCC"
      echo "$E/val_b${B}_s${s}_all $a val 200"
    done | xargs -P 2 -L 1 bash -c 'ev "$@"' _ ;;
  table)
    TAG="$T" EVAL_DIR="$E" "$PY" - <<'PYEOF'
import glob, json, os, re
T = os.environ["TAG"]; E = os.environ["EVAL_DIR"]
def d(path, bucket):
    x = json.load(open(path + "/summary.json"))["deltas"]["clean"][bucket]
    return x["iou_mean"]["delta"], x["iou_mean"]["ci95"]
print("| beta | 40-70% seed 0 | seed 1 | mean | unoccluded seed 0 | seed 1 | mean | rule |")
print("|---:|---:|---:|---:|---:|---:|---:|---|")
betas = sorted({int(re.search(r"val_b(\d+)_", p).group(1)) for p in glob.glob(f"{E}/val_b*_s0_all")})
for b in betas:
    paths = [f"{E}/val_b{b}_s{s}_{k}" for k in ("40_70", "all") for s in (0, 1)]
    if not all(os.path.exists(p + "/summary.json") for p in paths):
        print(f"| {b} | (missing) |"); continue
    occ = [d(f"{E}/val_b{b}_s{s}_40_70", "40-70%") for s in (0, 1)]
    unc = [d(f"{E}/val_b{b}_s{s}_all", "unoccluded") for s in (0, 1)]
    fmt = lambda r: f"{r[0]:+.4f} [{r[1][0]:+.4f}, {r[1][1]:+.4f}]"
    mo = sum(r[0] for r in occ) / 2; mu = sum(r[0] for r in unc) / 2
    print(f"| {b} | {fmt(occ[0])} | {fmt(occ[1])} | {mo:+.4f} | {fmt(unc[0])} | {fmt(unc[1])} | {mu:+.4f} | "
          f"{'eligible' if mu >= -0.01 else 'loses > 0.01 unoccluded'} |")
PYEOF
    ;;
  test)
    for s in 0 1; do
      a="runs/fmdpo_${T}_beta${B}_s$s/adapter"
      echo "$E/test_b${B}_s${s}_40_70 $a test 500 $OCC"
      echo "$E/test_b${B}_s${s}_all $a test 500"
      echo "$E/heldout_b${B}_s${s} $a heldout 100"
    done | xargs -P 2 -L 1 bash -c 'ev "$@"' _ ;;
  *) sed -n '2,12p' "$0" | sed 's/^# \{0,1\}//'; exit 2 ;;
esac
