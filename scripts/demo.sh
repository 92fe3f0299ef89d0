#!/usr/bin/env bash
# The main job end to end on an embedded default (called by ./run demo after setup and build):
#   1. a tiny synthetic FM-DPO pair cache             (pairs make)
#   2. FM-DPO training of LoRA adapters, a few steps  (train_fmdpo, small fixture model, CPU)
#   3. the adapter exported in PEFT format            (export_adapter)
#   4. a synthetic scene with one object of each probe branch (synth_bench --write): a hovering one
#      (stretch), one whose bottom is cut away as under occlusion (resample) and one hanging on the
#      wall (anchored)
#   5. the physics probe (configs/probe.yaml) with in-process resampling by the adapted Stage 1, best
#      of 4 samples, final settle, the 5 s evaluation settle of input and output, the paper's metrics,
#      MJCF, report and pictures (before_after.png, side_view.png, candidates_<id>.png)
#
# READ THIS: the demo's models have RANDOM weights (test fixtures, embedder random init; no trained
# SAM 3D weights are downloaded). The training step shows that the machinery runs, not that it
# learns anything useful, and every resampled shape is an arbitrary blob: a candidate is accepted only
# if it passes the probe's checks (penetration resolved, settles), and when none does the object keeps
# its input shape and is reported as NOT replaced. Stretch and anchoring do not depend on the weights.
# Collision shapes are one convex hull per mesh (--no-coacd): CoACD on random blobs takes minutes.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BUILD="${BUILD_DIR:-$ROOT/build}"
SHARED="${SIMU_SHARED_DIR:-$ROOT/../shared}"
FIX="$SHARED/fixtures"
OUT="${DEMO_OUT:-$ROOT/out/demo}"
cd "$ROOT"
rm -rf "$OUT" && mkdir -p "$OUT"
export SIMU_HULL_CACHE="$OUT/hull-cache"

cat <<'NOTE'
== This demo runs on RANDOM weights (small test fixtures; no trained SAM 3D weights are downloaded).
   It shows that every stage runs end to end, not results: the training loss means nothing, and any
   shape the resampler produces is an arbitrary blob. The physics probe (stretch, anchoring, checks,
   metrics) is real; a resampled candidate is kept only if it passes the probe's checks.
NOTE
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

echo "== 4/5 synthetic scene: a hovering object (stretch), a bottom-cut one (resample), a wall-hung one (anchored)"
"$BUILD/synth_bench" --scenes 1 --seed "${DEMO_SEED:-21}" --config configs/demo_scene.yaml --write "$OUT/scenes" >/dev/null
scene="$(ls "$OUT"/scenes/*/scene.json | head -1)"

echo "== 5/5 physics probe with in-process resampling (best of 4), final settle, metrics, MJCF, report, pictures"
cat <<'NOTE'
   NOTE: the generator, decoder and embedder below have RANDOM weights. Resampled shapes are
   meaningless blobs; the probe keeps a candidate only if it passes its physics checks, and otherwise
   keeps the input shape and says "NOT replaced". Stretch and wall anchoring do not use the weights.
NOTE
"$BUILD/probe" --config configs/probe.yaml --scene "$scene" --out "$OUT/probe" --resample --device cpu --steps 4 --seed 1 \
  --num-samples 4 \
  --generator-config "$FIX/ss_generator_small.json" --generator-weights "$FIX/ss_generator_small.safetensors" \
  --decoder-config configs/ss_decoder_small.yaml --decoder-weights "$FIX/ss_decoder_small.safetensors" \
  --embedder-config configs/demo_embedder_small.json --random-weights --adapter "$OUT/adapter" --no-coacd
# The demo shows all three branches of the probe; say so if the scene did not produce them.
PY="${SIMU_PYTHON:-$ROOT/.deps/venv/bin/python}"
"$PY" - "$OUT/probe/report.json" <<'PYEOF'
import json, sys
rep = json.load(open(sys.argv[1]))
branches = {o["branch"] for o in rep["objects"]}
missing = {"stretch", "resample", "anchored"} - branches
print("\nper-object summary (displacement in the 5 s evaluation settle; before = the input scene settled the same way)")
print(f"  {'object':<16} {'branch':<9} {'rho':>6} {'before':>10} {'after':>10}  flags")
for o in rep["objects"]:
    mm = lambda r: "-" if r is None or r["physics_disabled"] else f"{1000 * r['displacement']:.1f} mm"
    rho = "-" if o["branch"] == "disabled" else f"{o['rho']:.3f}"
    print(f"  {o['id']:<16} {o['branch']:<9} {rho:>6} {mm(o.get('evaluation_input')):>10} {mm(o['evaluation']):>10}  "
          + (",".join(o["flags"]) or "-"))
    if o["branch"] == "resample":
        r = o.get("resample", {})
        if r.get("resampled"):
            print(f"      replaced by resampled candidate #{r.get('chosen_candidate')} (random weights: an arbitrary shape that passed the checks)")
        else:
            print("      NOT replaced: no candidate passed the probe's checks; the input shape was kept")
if missing:
    sys.exit(f"demo: the scene did not exercise the {', '.join(sorted(missing))} branch (see report.json)")
PYEOF

echo
echo "demo outputs in $OUT:"
echo "  pair cache      $OUT/pairs.h5"
echo "  training run    $OUT/train (metrics.jsonl, TensorBoard events, checkpoints)"
echo "  PEFT adapter    $OUT/adapter"
echo "  input scene     $scene"
echo "  probe outputs   $OUT/probe"
echo "    final MJCF      $OUT/probe/scene.xml"
echo "    report          $OUT/probe/report.json"
echo "  pictures (look at these):"
echo "    before/after    $OUT/probe/before_after.png   (input masks left, final shaded meshes right)"
echo "    side view       $OUT/probe/side_view.png      (floating and sinking show here)"
for f in "$OUT"/probe/candidates_*.png; do [ -e "$f" ] && echo "    candidates      $f"; done
echo "    overlay         $OUT/probe/overlay.png        (masks, OBBs before/target, crop masks)"
echo "    corrected scene $OUT/probe/scene.json (+ meshes/)"
