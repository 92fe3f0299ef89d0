#!/usr/bin/env bash
# Prepares, on our Debian 12 machine, what the GPU machine's image lacks, as files under .carry/:
#   .carry/prefix/usr/...  Debian packages unpacked (MuJoCo 2.2.2 + qhull, assimp, GoogleTest, the gloo
#                          headers of libgloo-dev for c10d ProcessGroupGloo; never linked) and
#                          the runtime libraries they need; CoACD's C library from its PyPI wheel; the cuDNN
#                          frontend's headers from its PyPI wheel (bench_cudnn_sdpa)
#   .carry/shared/         the fixtures the GPU tests read, from ../shared/fixtures (the device gets only the
#                          repository); the 55 MB preprocess_released_* fixtures are CPU-only and stay here
# The GPU machine has LibTorch (its PyTorch 2.11.0+cu130), CUDA, Eigen, HDF5 1.10, yaml-cpp, CLI11,
# nlohmann-json. OpenCV is NOT carried: Debian's imgcodecs pulls GDAL (~180 MB of libraries), over the
# device's 64 MiB transfer limit; the GPU build sets SIMU_WITH_OPENCV=OFF (image-file tests skip there).
# Then run on the device (carry .carry):  bash scripts/gpu_build_test.sh
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
CARRY="$ROOT/.carry"
SHARED="${SIMU_SHARED_DIR:-$ROOT/../shared}"
PKGS=(libmujoco-dev libmujoco2.2.2 libqhull-dev libqhull-r8.0 libqhull8.0 libqhullcpp8.0 libccd2 libtinyxml2-9
      liblodepng0 libassimp-dev libassimp5 libdraco7 libminizip1 libgtest-dev libgmock-dev libpoly2tri1 libpugixml1v5
      libkubazip0 libgloo-dev libre2-dev libre2-9 libnanoflann-dev)
mkdir -p "$CARRY/debs" "$CARRY/prefix"
cd "$CARRY/debs"
for p in "${PKGS[@]}"; do
  ls "${p}"_*.deb >/dev/null 2>&1 || apt-get download -qq "$p" 2>/dev/null || echo "[bundle] note: no package $p (skipped)"
done
for d in "$CARRY"/debs/*.deb; do dpkg -x "$d" "$CARRY/prefix"; done
# CoACD's C library from the venv's PyPI package, when installed.
coacd_lib="$(ls "$ROOT"/.deps/venv/lib/python3*/site-packages/coacd/lib_coacd.so 2>/dev/null | head -1 || true)"
if [ -n "$coacd_lib" ]; then
  mkdir -p "$CARRY/prefix/usr/lib/coacd" && cp -f "$coacd_lib" "$CARRY/prefix/usr/lib/coacd/"
  cp -f "$(dirname "$coacd_lib")"/../coacd.libs/*.so* "$CARRY/prefix/usr/lib/coacd/" 2>/dev/null || true  # its vendored libgomp
fi
# The cuDNN frontend's headers (PyPI nvidia-cudnn-frontend, header-only) for bench_cudnn_sdpa, found by CMake
# under the prefix; cudnn.h itself comes with the image's torch (nvidia/cudnn/include).
fe_inc="$(ls -d "$ROOT"/.deps/venv/lib/python3*/site-packages/include 2>/dev/null | head -1 || true)"
if [ -n "$fe_inc" ] && [ -f "$fe_inc/cudnn_frontend.h" ]; then
  mkdir -p "$CARRY/prefix/usr/include" && cp -r "$fe_inc"/cudnn_frontend* "$fe_inc"/cudnn_backend_base.h "$CARRY/prefix/usr/include/"
fi
# Fixtures.
rm -rf "$CARRY/shared" && mkdir -p "$CARRY/shared/fixtures"
for f in "$SHARED"/fixtures/*; do
  case "$(basename "$f")" in preprocess_released_*) continue;; esac  # CPU tests only (64 MiB transfer limit)
  cp -r "$f" "$CARRY/shared/fixtures/"
done
rm -rf "$CARRY/prefix/usr/share/doc" "$CARRY/prefix/usr/share/man"
du -sh "$CARRY/prefix" "$CARRY/shared"
