#!/usr/bin/env bash
# Builds the tree on the GPU machine and runs every test, the `gpu`-labelled ones included.
# Needs .carry/ from scripts/gpu_bundle.sh (run here first) carried with the device call:
#   device run (carry .carry): bash scripts/gpu_build_test.sh [ctest args]
# Uses the machine's own PyTorch 2.11.0+cu130 (python3) for LibTorch. Writes build-gpu/ (BUILD_DIR overrides).
# SIMU_CMAKE_ARGS adds configure options, e.g. the sanitizer suite on the device's 16 cores:
#   BUILD_DIR=build-asan SIMU_CMAKE_ARGS=-DSIMU_SANITIZE=ON CUDA_VISIBLE_DEVICES= \
#   ASAN_OPTIONS=detect_leaks=0:protect_shadow_gap=0 bash scripts/gpu_build_test.sh -LE gpu
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
source "$ROOT/scripts/gpu_env.sh"
BUILD="${BUILD_DIR:-$ROOT/build-gpu}"
t0=$(date +%s)
# SIMU_CMAKE_ARGS: extra configure options (word-split on purpose).
# shellcheck disable=SC2086
gpu_configure "$BUILD" "$ROOT/gpu-configure.log" ${SIMU_CMAKE_ARGS:-} || exit 1
grep -E "gloo headers" "$ROOT/gpu-configure.log" || true  # c10d ProcessGroupGloo for CPU ranks (headers from .carry)
cmake --build "$BUILD" -j"$(nproc)" >"$ROOT/gpu-build.log" 2>&1 || { grep -B2 -A8 -E "error|FAILED" "$ROOT/gpu-build.log" | head -80; exit 1; }
t1=$(date +%s)
echo "[gpu] configure+build: $((t1 - t0)) s on $(nproc) cores"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
cd "$BUILD"
ctest --output-on-failure --timeout 900 -j4 "$@"
