# Sourced by the GPU-machine scripts (gpu_build_test.sh, gpu_lift_speed.sh, gpu_bench.sh): the environment
# of a device run with .carry/ (scripts/gpu_bundle.sh), and the CMake configure they share. Needs ROOT.
#   gpu_configure BUILD_DIR LOG [cmake args...]   configure a Release build against the machine's PyTorch
PREFIX="$ROOT/.carry/prefix/usr"
[ -d "$PREFIX" ] || { echo "error: $PREFIX missing: run scripts/gpu_bundle.sh here and carry .carry" >&2; exit 1; }
export LD_LIBRARY_PATH="$PREFIX/lib/x86_64-linux-gnu:$PREFIX/lib/coacd:${LD_LIBRARY_PATH:-}"
export SIMU_SHARED_DIR="${SIMU_SHARED_DIR:-$ROOT/.carry/shared}"
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
gpu_configure() {
  local build="$1" log="$2"
  shift 2
  local py="${PYTHON:-python3}"
  local torch_prefix
  torch_prefix="$("$py" -c 'import torch.utils; print(torch.utils.cmake_prefix_path)')"
  cmake -S "$ROOT" -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DCMAKE_PREFIX_PATH="$torch_prefix;$PREFIX" \
    -DSIMU_WITH_OPENCV=OFF -DSIMU_PYTHON="$(command -v "$py")" -DSIMU_COACD_DIR="$PREFIX/lib/coacd" \
    -DTORCH_CUDA_ARCH_LIST=9.0 "$@" >"$log" 2>&1 || { tail -40 "$log"; return 1; }
}
