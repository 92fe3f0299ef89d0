#!/usr/bin/env bash
# Behaviour identity of two builds (issue 34: a layout move must not change what the programs do).
# Runs the same jobs with both builds' programs on this machine and compares the outputs byte for byte:
#   1. the CPU training run's adapter: pairs make -> train_fmdpo configs/tiny.yaml -> export_adapter
#   2. synth_bench's tables (20 scenes, MuJoCo probe; its timing lines are left out)
#   3. the probe with in-process resampling on a written synth_bench scene (the demo's step 5, random
#      fixture weights): report.json without its seconds, scene.xml, the output scene.json
#   bash scripts/behaviour_identity.sh OLD_ROOT OLD_BUILD NEW_ROOT NEW_BUILD OUT_DIR
# Each ROOT is the source tree its build was made from (configs are read from it). Needs the fixtures
# (SIMU_SHARED_DIR or ../shared). Exit status 1 when any output differs.
set -uo pipefail
[ $# -eq 5 ] || { echo "usage: $0 OLD_ROOT OLD_BUILD NEW_ROOT NEW_BUILD OUT_DIR" >&2; exit 2; }
OUT="$5"
FIX="${SIMU_SHARED_DIR:-$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)/shared}/fixtures"
PY="${PYTHON:-python3}"
mkdir -p "$OUT"

# run_jobs ROOT BUILD DIR: every job of one build into DIR.
run_jobs() {
  local root="$1" build="$2" dir="$3"
  rm -rf "$dir" && mkdir -p "$dir"
  (
    cd "$root" || exit 1
    "$build/pairs" make --out "$dir/pairs.h5" --n 16 --tokens 64 --channels 8 --cond-len 10 --cond-channels 48 --seed 1
    "$build/train_fmdpo" --config configs/tiny.yaml --set "model.config=$FIX/ss_generator_small.json" \
      --set "model.weights=$FIX/ss_generator_small.safetensors" --set "data.cache=$dir/pairs.h5" \
      --set "run.out_dir=$dir/train" --set train.device=cpu
    ckpt="$(ls -d "$dir"/train/checkpoints/step_* | sort -V | tail -1)"
    "$build/export_adapter" "$ckpt" "$dir/adapter" --config configs/tiny.yaml
    "$build/synth_bench" --scenes 20 --seed 7 --threads 4 >"$dir/synth_bench.txt"
    "$build/synth_bench" --scenes 1 --seed 21 --config configs/demo_scene.yaml --write "$dir/scenes" >/dev/null
    scene="$(ls "$dir"/scenes/*/scene.json | head -1)"
    SIMU_HULL_CACHE="$dir/hull-cache" "$build/probe" --config configs/probe.yaml --scene "$scene" --out "$dir/probe" \
      --resample --device cpu --steps 4 --seed 1 --num-samples 4 \
      --generator-config "$FIX/ss_generator_small.json" --generator-weights "$FIX/ss_generator_small.safetensors" \
      --decoder-config configs/ss_decoder_small.yaml --decoder-weights "$FIX/ss_decoder_small.safetensors" \
      --embedder-config configs/demo_embedder_small.json --random-weights --adapter "$dir/adapter" --no-coacd
  ) >"$dir.log" 2>&1
  echo "[identity] $build: rc $? (log $dir.log)"
}
run_jobs "$1" "$2" "$OUT/old"
run_jobs "$3" "$4" "$OUT/new"

# Compare: files byte for byte; report.json without the keys that hold wall-clock seconds; synth_bench
# without lines that print timings.
"$PY" - "$OUT/old" "$OUT/new" <<'PYEOF'
import hashlib, json, os, re, sys
old, new = sys.argv[1], sys.argv[2]
def strip(o):
    if isinstance(o, dict):
        return {k: strip(v) for k, v in o.items() if not re.search(r"(second|time|elapsed|_s$|^s$|date|host|path|dir|^scene$|^image$|^depth$)", k)}
    if isinstance(o, list):
        return [strip(v) for v in o]
    return o
def digest(path, root):
    # The run's own folder is named in some outputs (mesh paths): it is the one thing allowed to differ.
    if path.endswith(".json") and not path.endswith("adapter_config.json"):
        text = open(path).read().replace(root, "<DIR>")
        return hashlib.sha256(json.dumps(strip(json.loads(text)), sort_keys=True).encode()).hexdigest()
    if path.endswith(".xml"):
        return hashlib.sha256(open(path).read().replace(root, "<DIR>").encode()).hexdigest()
    if path.endswith("synth_bench.txt"):
        lines = [l for l in open(path) if not re.search(r"\bs\b|seconds|ms\b|time", l)]
        return hashlib.sha256("".join(lines).encode()).hexdigest()
    return hashlib.sha256(open(path, "rb").read()).hexdigest()
checked = ["adapter/adapter_model.safetensors", "adapter/adapter_config.json", "synth_bench.txt",
           "probe/report.json", "probe/scene.xml", "probe/scene.json"]
bad = 0
for rel in checked:
    a, b = os.path.join(old, rel), os.path.join(new, rel)
    if not (os.path.exists(a) and os.path.exists(b)):
        print(f"MISSING  {rel}: old {os.path.exists(a)} new {os.path.exists(b)}"); bad += 1; continue
    da, db = digest(a, old), digest(b, new)
    print(f"{'same' if da == db else 'DIFFERS':8} {rel}  {da[:16]}" + ("" if da == db else f" vs {db[:16]}"))
    bad += da != db
sys.exit(1 if bad else 0)
PYEOF
