#!/usr/bin/env bash
# Preference pairs on a tiny world, end to end (ctest: WorldPairs.BuildAndFilter): `world pairs` writes
# 3 occlusion-completion and 3 clean-preservation pairs of train scenes; `build_pairs --filter-gt` with
# the shipped miniature (CPU) samples both sides of each, decodes them and keeps a pair only when x+
# is closer to the ground-truth occupancy than x-. Checked (tests/pipeline/resample/world_pairs_check.py):
# the manifest's keys and files, both kinds, every pair judged, the kept ones exactly those with
# IoU(x+) > IoU(x-), and the cache holding exactly the kept ids.
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
