// libFuzzer target: the geometry inputs of `lift` and the probe (src/data/depth_io.cpp): .npy arrays
// (read_npy_header, read_npy, read_depth, read_pointmap, then estimate_intrinsics / unproject_depth on
// what was read), 16-bit PNG depth in millimetres and label images, OpenEXR depth, and camera
// intrinsics JSON. Input: first byte selects what the rest is: 0-63 .npy, 64-127 .png, 128-191 .exr,
// 192-255 K .json. Anything but a simu::Error escaping a reader is a finding.
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "common/error.h"
#include "data/depth_io.h"

namespace sd = simu::data;

namespace {
// SIMU_FUZZ_VERBOSE=1: print each reader's error (to check what a seed or a crash input reaches).
void note(const simu::Error& e) {
  static const bool verbose = std::getenv("SIMU_FUZZ_VERBOSE") != nullptr;
  if (verbose) std::fprintf(stderr, "error: %s\n", e.what());
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  const uint8_t sel = data[0];
  const char* ext = sel < 64 ? ".npy" : sel < 128 ? ".png" : sel < 192 ? ".exr" : ".json";
  static const std::string base = [] {
    const char* dir = std::getenv("SIMU_FUZZ_TMP");
    return std::string(dir ? dir : "/tmp") + "/simu_fuzz_depth_" + std::to_string(::getpid());
  }();
  const std::string path = base + ext;
  FILE* f = std::fopen(path.c_str(), "wb");
  if (!f) return 0;
  std::fwrite(data + 1, 1, size - 1, f);
  std::fclose(f);
  const sd::Intrinsics K{100.0, 100.0, 2.0, 2.0};
  if (sel < 64) {
    try {
      (void)sd::read_npy(path);
    } catch (const simu::Error& e) {
      note(e);
    }
    try {
      const auto z = sd::read_depth(path);
      (void)sd::unproject_depth(z, K);
    } catch (const simu::Error& e) {
      note(e);
    }
    try {
      const auto p = sd::read_pointmap(path);
      (void)sd::estimate_intrinsics(p, path);
    } catch (const simu::Error& e) {
      note(e);
    }
  } else if (sel < 192) {
    try {
      const auto z = sd::read_depth(path);
      (void)sd::unproject_depth(z, K);
    } catch (const simu::Error& e) {
      note(e);
    }
    if (sel < 128) {
      try {
        (void)sd::read_label_image(path);
      } catch (const simu::Error& e) {
        note(e);
      }
    }
  } else {
    try {
      (void)sd::read_intrinsics_json(path);
    } catch (const simu::Error& e) {
      note(e);
    }
  }
  return 0;
}
