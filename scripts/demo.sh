#!/usr/bin/env bash
# The main job end to end on an embedded default (called by ./run demo after setup and build):
#   1. a tiny synthetic FM-DPO pair cache             (pairs make)
#   2. FM-DPO training of LoRA adapters, a few steps  (train_fmdpo, small fixture model, CPU)
#   3. the adapter exported in PEFT format            (export_adapter)
#   4. a synthetic scene whose one object has its bottom cut away (synth_bench --write)
#   5. the physics probe with in-process resampling by the adapted Stage 1, best of 4 samples,
#      final settle -> MJCF + overlay PNG + report + corrected scene   (probe --resample; run_probe writes overlay.png)
# The small models have RANDOM weights (fixtures, embedder random init), so the decoded shapes and
# poses are arbitrary and often too large for the table: candidates whose penetration resolution
# fails are rejected, the one that moves least is kept; when none settles the probe keeps the one that
# penetrated least (flag no_stable_candidate) and the final settle may revert it. report.json has the
# figures of every candidate. Collision shapes are one convex hull per mesh (--no-coacd): CoACD on
# these random blobs takes minutes.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BUILD="${BUILD_DIR:-$ROOT/build}"
SHARED="${SIMU_SHARED_DIR:-$ROOT/../shared}"
FIX="$SHARED/fixtures"
OUT="${DEMO_OUT:-$ROOT/out/demo}"
cd "$ROOT"
rm -rf "$OUT" && mkdir -p "$OUT"
export SIMU_HULL_CACHE="$OUT/hull-cache"

echo "== 1/5 synthetic pair cache"
"$BUILD/pairs" make --out "$OUT/pairs.h5" --n 16 --tokens 64 --channels 8 --cond-len 10 --cond-channels 48 --seed 1
"$BUILD/pairs" validate "$OUT/pairs.h5"

echo "== 2/5 FM-DPO training (small fixture generator, LoRA r 4, 6 steps, CPU)"
"$BUILD/train_fmdpo" --config configs/tiny.yaml \
  --set "model.config=$FIX/ss_generator_small.json" --set "model.weights=$FIX/ss_generator_small.safetensors" \
  --set "data.cache=$OUT/pairs.h5" --set "run.out_dir=$OUT/train"

echo "== 3/5 adapter export (PEFT format)"
ckpt="$(ls -d "$OUT"/train/checkpoints/step_* | sort -V | tail -1)"
"$BUILD/export_adapter" "$ckpt" "$OUT/adapter" --config configs/tiny.yaml

echo "== 4/5 synthetic scene: one object with its bottom cut away"
"$BUILD/synth_bench" --scenes 1 --seed 3 --config configs/demo_scene.yaml --write "$OUT/scenes" >/dev/null
scene="$(ls "$OUT"/scenes/*/scene.json | head -1)"

echo "== 5/5 physics probe with in-process resampling (best of 4), final settle, MJCF, overlay, report"
PY="${SIMU_PYTHON:-$ROOT/.deps/venv/bin/python}"
"$BUILD/probe" --scene "$scene" --out "$OUT/probe" --resample --device cpu --steps 4 --seed 1 --num-samples 4 \
  --generator-config "$FIX/ss_generator_small.json" --generator-weights "$FIX/ss_generator_small.safetensors" \
  --decoder-config configs/ss_decoder_small.yaml --decoder-weights "$FIX/ss_decoder_small.safetensors" \
  --embedder-config configs/demo_embedder_small.json --random-weights --adapter "$OUT/adapter" --no-coacd
# The demo's point: the cut object must have been replaced by the resampled mesh.
"$PY" - "$OUT/probe/report.json" <<'PYEOF'
import json, sys
rep = json.load(open(sys.argv[1]))
res = [o for o in rep["objects"] if o["branch"] == "resample"]
if not res or not all(o.get("resample", {}).get("resampled") for o in res):
    sys.exit("demo: the resampled object was not replaced (see report.json)")
for o in res:
    r = o["resample"]
    print(f"  {o['id']}: replaced; candidates " + ", ".join(
        f"#{k} {'moved %.3f m' % c['displacement'] if c['ok'] else 'failed'}{' (kept)' if c['chosen'] else ''}"
        for k, c in enumerate(r.get("candidates", []))))
PYEOF

echo
echo "demo outputs in $OUT:"
echo "  pair cache      $OUT/pairs.h5"
echo "  training run    $OUT/train (metrics.jsonl, TensorBoard events, checkpoints)"
echo "  PEFT adapter    $OUT/adapter"
echo "  input scene     $scene"
echo "  probe outputs   $OUT/probe"
echo "    final MJCF      $OUT/probe/scene.xml"
echo "    overlay PNG     $OUT/probe/overlay.png"
echo "    report          $OUT/probe/report.json"
echo "    corrected scene $OUT/probe/scene.json (+ meshes/)"
