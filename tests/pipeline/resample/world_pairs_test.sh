#!/usr/bin/env bash
# Preference pairs on a tiny world, end to end (ctest: WorldPairs.BuildAndFilter): `world pairs` writes
# 3 occlusion-completion and 3 clean-preservation pairs of train scenes; `build_pairs --filter-gt` with
# the shipped miniature (CPU) samples both sides of each, decodes them and keeps a pair only when x+
# is closer to the ground-truth occupancy than x-. Checked (tests/pipeline/resample/world_pairs_check.py):
# the manifest's keys and files, both kinds, every pair judged, the kept ones exactly those with
# IoU(x+) > IoU(x-), and the cache holding exactly the kept ids. The same manifest with x+ from the
# ground truth (--preferred gt-latent): every x+ decodes back to its ground truth. Then 3 FM-DPO steps of the miniature's
# recipe (configs/miniature_cpu/lora.yaml) on that cache: finite losses and a PEFT adapter of rank 8.
#   bash tests/pipeline/resample/world_pairs_test.sh BUILD_DIR REPO_ROOT
set -euo pipefail
if [[ $# -ne 2 ]]; then
  echo "usage: $0 BUILD_DIR REPO_ROOT" >&2
  exit 2
fi
BUILD=$(cd "$1" && pwd)
REPO=$(cd "$2" && pwd)
PY="${SIMU_PYTHON:-$REPO/.deps/venv/bin/python}"
TMP=$(mktemp -d "${TMPDIR:-/tmp}/world_pairs.XXXXXX")
trap 'rm -rf "$TMP"' EXIT
cd "$REPO"
"$BUILD/world" pairs --completion 3 --preservation 3 --seed 0 --out "$TMP/pairs" --threads 2
"$BUILD/build_pairs" --manifest "$TMP/pairs/manifest.jsonl" --out "$TMP/pairs.h5" --device cpu --filter-gt \
  --report "$TMP/report.json" --batch 6
"$PY" "$REPO/tests/pipeline/resample/world_pairs_check.py" "$TMP/pairs" "$TMP/report.json" "$TMP/pairs.h5"
# x+ from the ground truth (--preferred gt-latent, the shipped miniature's encoder), same manifest: every
# pair's x+ must decode back to its gt_occupancy as the VAE reconstructs (the filter's iou_pos >= 0.85:
# the VAE's worst seen-family test reconstruction is 0.887, runs/ss_vae_cpu/eval.json; a latent in the
# wrong token order or channel layout decodes to noise), and the cache must say where x+ came from.
"$BUILD/build_pairs" --manifest "$TMP/pairs/manifest.jsonl" --out "$TMP/pairs_gt.h5" --device cpu --filter-gt \
  --report "$TMP/report_gt.json" --batch 6 --preferred gt-latent
"$PY" - "$TMP/report_gt.json" "$TMP/pairs_gt.h5" <<'PYEOF'
import json, sys
import h5py
rep = json.load(open(sys.argv[1]))
assert rep["preferred"] == "gt_latent", rep["preferred"]
rows = rep["filtered"]
assert len(rows) == 6 and not rep["issues"], (len(rows), rep["issues"])
assert all(r["iou_pos"] >= 0.85 for r in rows), [round(r["iou_pos"], 3) for r in rows]
with h5py.File(sys.argv[2], "r") as f:
    by = f.attrs["created_by"]
    by = by.decode() if isinstance(by, bytes) else str(by)
    assert "x+ = ground-truth encoder latent" in by, by
print("gt-latent pairs ok: x+ decodes to IoU", [round(r["iou_pos"], 3) for r in rows], "x-", [round(r["iou_neg"], 3) for r in rows])
PYEOF
[ -f "$TMP/pairs.h5" ] || { echo "the filter kept no pair: no FM-DPO steps to run"; exit 0; }
"$BUILD/train_fmdpo" --config configs/miniature_cpu/lora.yaml --set "data.cache=$TMP/pairs.h5" --set train.steps=3 \
  --set optim.warmup_steps=1 --set data.global_batch=1 --set data.micro_batch=1 --set run.out_dir="$TMP/fmdpo" \
  --set run.checkpoint_every=0 --set run.log_every=1
"$PY" - "$TMP/fmdpo" <<'PYEOF'
import json, math, sys
d = sys.argv[1]
rows = [json.loads(l) for l in open(d + "/metrics.jsonl") if l.strip()]
assert len(rows) == 3 and all(math.isfinite(r["loss"]) for r in rows), rows
# Step 1: LoRA's B starts at zero, so policy == reference and the DPO loss is -log sigmoid(0) = log 2,
# times the weight of the step's one pair (its kind from the per-kind metrics; the weights from the config
# trained with) (fp32 flow losses of one pair: far below the 1e-4 allowed).
import re
kinds = {k.split("/")[0] for k in rows[0] if k.startswith(("completion/", "preservation/"))}
assert len(kinds) == 1, rows[0]
kind = kinds.pop()
cfg_text = open("configs/miniature_cpu/lora.yaml").read()
w = float(re.search(r"^\s*weight_%s:\s*([0-9.eE+-]+)" % kind, cfg_text, re.M).group(1))
assert abs(rows[0]["loss"] - w * math.log(2)) < 1e-4, (kind, w, rows[0])
cfg = json.load(open(d + "/adapter/adapter_config.json"))
assert cfg["r"] == 8 and cfg["lora_alpha"] == 16, cfg
print("fmdpo ok: losses", [round(r["loss"], 4) for r in rows])
PYEOF
