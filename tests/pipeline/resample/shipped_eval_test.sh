#!/usr/bin/env bash
# The shipped miniature still makes the shapes it was shipped with (ctest: ShippedModel.Evaluation).
#   bash tests/pipeline/resample/shipped_eval_test.sh BUILD_DIR REPO_ROOT
# Loads weights/miniature_cpu (as every program does when given no weights), runs eval_lift on the CPU
# on the fixed subset its manifest records under "ci_check" (20 test-split objects, seed 0, the
# clean and corrupted point maps), and fails when a recorded metric falls below its recorded value
# minus the manifest's stated tolerance (tests/pipeline/resample/shipped_eval_check.py says where the
# tolerance comes from). A change that silently breaks the model path (loading, preprocessing,
# embedder, sampler, decoder, pose) moves these far more than the tolerance. Then the shipped FM-DPO
# resampling adapter's recorded paired deltas (manifest "ci_check_adapter"), when there is one.
set -euo pipefail
if [[ $# -ne 2 ]]; then
  echo "usage: $0 BUILD_DIR REPO_ROOT" >&2
  exit 2
fi
BUILD=$(cd "$1" && pwd)
REPO=$(cd "$2" && pwd)
PY="${SIMU_PYTHON:-$REPO/.deps/venv/bin/python}"
MANIFEST="$REPO/weights/miniature_cpu/manifest.json"
[ -f "$MANIFEST" ] || { echo "FAIL: $MANIFEST missing (the shipped miniature)" >&2; exit 1; }
TMP=$(mktemp -d "${TMPDIR:-/tmp}/shipped_eval.XXXXXX")
trap 'rm -rf "$TMP"' EXIT
# The recorded command's arguments, from the manifest (so the check and the record cannot drift).
mapfile -t ARGS < <("$PY" -c 'import json,sys; [print(a) for a in json.load(open(sys.argv[1]))["ci_check"]["args"]]' "$MANIFEST")
(cd "$REPO" && "$BUILD/eval_lift" "${ARGS[@]}" --device cpu --no-pictures --out "$TMP/eval")
"$PY" "$REPO/tests/pipeline/resample/shipped_eval_check.py" "$MANIFEST" "$TMP/eval/summary.json"
# The shipped resampling adapter (weights/miniature_cpu/adapter), when the manifest records its check:
# base and base + adapter on the recorded objects; each recorded paired delta must hold (an adapter
# that no longer loads or no longer applies gives a delta of exactly 0).
if "$PY" -c 'import json,sys; sys.exit(0 if "ci_check_adapter" in json.load(open(sys.argv[1])) else 1)' "$MANIFEST"; then
  mapfile -t AARGS < <("$PY" -c 'import json,sys; [print(a) for a in json.load(open(sys.argv[1]))["ci_check_adapter"]["args"]]' "$MANIFEST")
  (cd "$REPO" && "$BUILD/eval_lift" "${AARGS[@]}" --device cpu --no-pictures --out "$TMP/eval_adapter")
  "$PY" "$REPO/tests/pipeline/resample/shipped_eval_check.py" "$MANIFEST" "$TMP/eval_adapter/summary.json" adapter
fi
