#!/usr/bin/env bash
# Brings a fresh Debian 12 machine to a configured and built tree.
# Idempotent: every step checks first and stays quiet when nothing is to do.
#   scripts/setup.sh            install what is missing, configure, build
#   scripts/setup.sh --deps     install only (no configure/build)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

# Pinned versions (Debian 12 "bookworm" pins the system packages; these are checked).
TORCH_VERSION="2.11.0"          # same as the GPU machine's PyTorch 2.11.0+cu130
MUJOCO_VERSION_PREFIX="2.2.2"
DEPS="$ROOT/.deps"
VENV="$DEPS/venv"
BUILD="${BUILD_DIR:-$ROOT/build}"

log() { printf '[setup] %s\n' "$*"; }

# Debian packages the build and the tests need.
APT_PKGS=(
  build-essential cmake ninja-build ccache pkg-config
  libmujoco-dev libqhull-dev
  libhdf5-dev
  libopencv-core-dev libopencv-imgproc-dev libopencv-imgcodecs-dev
  libeigen3-dev libyaml-cpp-dev libgtest-dev libgmock-dev
  libcli11-dev nlohmann-json3-dev libassimp-dev
  libgloo-dev
  libre2-dev
  libnanoflann-dev
  clang libclang-rt-dev
  python3-venv python3-dev
)
missing=()
for p in "${APT_PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  log "installing Debian packages: ${missing[*]}"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
mj="$(dpkg-query -W -f='${Version}' libmujoco-dev)"
case "$mj" in "$MUJOCO_VERSION_PREFIX"*) ;; *) echo "[setup] error: libmujoco-dev $mj found, $MUJOCO_VERSION_PREFIX expected" >&2; exit 1;; esac

# LibTorch from PyPI's torch wheel, in a git-ignored virtual environment of the project.
if ! [ -f "$VENV/.torch-$TORCH_VERSION" ]; then
  log "installing torch==$TORCH_VERSION (PyPI wheel, CUDA 13 build) into $VENV"
  mkdir -p "$DEPS"
  python3 -m venv "$VENV"
  "$VENV/bin/python" -m pip install -q --upgrade pip
  "$VENV/bin/python" -m pip install -q "torch==$TORCH_VERSION" "numpy<3" "safetensors==0.7.0" "h5py==3.15.1" "tensorboard==2.20.0"
  touch "$VENV/.torch-$TORCH_VERSION"
fi
# CoACD (convex decomposition for the physics probe): its wheel ships lib_coacd.so with a C API.
COACD_VERSION="1.0.14"
if ! [ -f "$VENV/.coacd-$COACD_VERSION" ]; then
  log "installing coacd==$COACD_VERSION into $VENV"
  "$VENV/bin/python" -m pip install -q "coacd==$COACD_VERSION"
  touch "$VENV/.coacd-$COACD_VERSION"
fi

# PyPI nvidia-cudnn-frontend: cuDNN's header-only C++ frontend (its include/ lands in site-packages), for
# bench_cudnn_sdpa, which builds cuDNN attention graphs against the libcudnn LibTorch loads.
CUDNN_FE_VERSION="1.32.0"
if ! [ -f "$VENV/.cudnn-frontend-$CUDNN_FE_VERSION" ]; then
  log "installing nvidia-cudnn-frontend==$CUDNN_FE_VERSION into $VENV"
  "$VENV/bin/python" -m pip install -q "nvidia-cudnn-frontend==$CUDNN_FE_VERSION"
  touch "$VENV/.cudnn-frontend-$CUDNN_FE_VERSION"
fi

# PyPI mujoco: the scene.xml check runs the probe's output in the MuJoCo users open it in (tests/pipeline/physics/mjcf_rest_check.py).
MUJOCO_PY_VERSION="4.0.0"
if ! [ -f "$VENV/.mujoco-$MUJOCO_PY_VERSION" ]; then
  log "installing mujoco==$MUJOCO_PY_VERSION into $VENV"
  "$VENV/bin/python" -m pip install -q "mujoco==$MUJOCO_PY_VERSION"
  touch "$VENV/.mujoco-$MUJOCO_PY_VERSION"
fi

# The Python module's test and type-check tools, and the packages its tests hand results to (tests/python,
# docs/python.md); scikit-build-core builds the wheel (pip install --no-build-isolation .).
PY_TEST_PINS=("pytest==9.2.0" "mypy==2.4.1" "trimesh==5.2.0" "peft==0.21.2" "scikit-build-core==1.1.2")
PY_TEST_STAMP="$VENV/.pytools-$(printf '%s' "${PY_TEST_PINS[*]}" | md5sum | cut -c1-12)"
if ! [ -f "$PY_TEST_STAMP" ]; then
  log "installing ${PY_TEST_PINS[*]} into $VENV"
  "$VENV/bin/python" -m pip install -q "${PY_TEST_PINS[@]}"
  touch "$PY_TEST_STAMP"
fi

[ "${1:-}" = "--deps" ] && exit 0

# Configure (once) and build.
TORCH_PREFIX="$("$VENV/bin/python" -c 'import torch.utils; print(torch.utils.cmake_prefix_path)')"
if ! [ -f "$BUILD/build.ninja" ]; then
  log "configuring $BUILD"
  cmake -S "$ROOT" -B "$BUILD" -G Ninja -DCMAKE_BUILD_TYPE=Release \
    -DCMAKE_PREFIX_PATH="$TORCH_PREFIX" -DSIMU_PYTHON="$VENV/bin/python" >/dev/null
fi
cmake --build "$BUILD" -- -j"${JOBS:-$(nproc)}" >"$BUILD/build.log" 2>&1 || { tail -n 60 "$BUILD/build.log" >&2; echo "[setup] build failed: full log in $BUILD/build.log" >&2; exit 1; }

# The Python module into the project's venv (pip install --no-build-isolation . reuses this build tree:
# only the install step runs). Skipped where .deps is a link to another checkout's venv (git worktrees
# share the main checkout's), so a worktree never installs its branch into someone else's environment;
# and for other BUILD_DIRs (pyproject.toml names build/).
MODULE="$(ls "$BUILD"/python/simuscene/_core*.so 2>/dev/null | head -1)"
if [ -n "$MODULE" ] && [ "$BUILD" = "$ROOT/build" ] && ! [ -L "$DEPS" ] && { ! [ -f "$VENV/.simuscene-installed" ] || [ "$MODULE" -nt "$VENV/.simuscene-installed" ]; }; then
  log "installing the simuscene Python package into $VENV (pip install --no-build-isolation .)"
  "$VENV/bin/python" -m pip install -q --no-build-isolation --no-deps "$ROOT" >"$BUILD/pip-install.log" 2>&1 ||
    { tail -n 30 "$BUILD/pip-install.log" >&2; echo "[setup] pip install of the Python package failed: $BUILD/pip-install.log" >&2; exit 1; }
  touch "$VENV/.simuscene-installed"
fi
