#!/usr/bin/env bash
# The main job on an embedded default (called by ./run demo after setup and build).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BUILD="${BUILD_DIR:-$ROOT/build}"
SHARED="${SIMU_SHARED_DIR:-$ROOT/../shared}"
OUT="${DEMO_OUT:-$ROOT/out/demo}"
mkdir -p "$OUT"
echo "== demo: official-layout small checkpoint from $SHARED/fixtures"
"$BUILD/inspect_safetensors" "$SHARED/fixtures/ss_generator_small.safetensors" --filter blocks.0.self_attn
echo "== demo outputs in $OUT"
