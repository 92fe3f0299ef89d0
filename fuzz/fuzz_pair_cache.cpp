// libFuzzer target: an HDF5 pair cache as `pairs inspect`, `pairs validate` and train_fmdpo open it:
// PairCacheReader::open (attributes, datasets, dtypes, shapes, kinds, ids), record reads, and the
// full validate_cache scan. Input: the file's bytes (written to a private temporary file).
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <string>

#include "common/error.h"
#include "data/pair_cache.h"

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  // HDF5 prints its own error stacks only when asked; keep the fuzzer's output readable.
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const std::string path = [] {
    const char* dir = std::getenv("SIMU_FUZZ_TMP");
    return std::string(dir ? dir : "/tmp") + "/simu_fuzz_pairs_" + std::to_string(::getpid()) + ".h5";
  }();
  FILE* f = std::fopen(path.c_str(), "wb");
  if (!f) return 0;
  std::fwrite(data, 1, size, f);
  std::fclose(f);
  try {
    const auto reader = simu::data::PairCacheReader::open(path);
    const int64_t n = std::min<int64_t>(reader.size(), 4);
    for (int64_t i = 0; i < n; ++i) (void)reader.read(i);
    (void)reader.ids();
    (void)reader.kinds();
    (void)reader.weights();
    (void)simu::data::describe_datasets(path);
  } catch (const simu::Error&) {
  } catch (const c10::Error&) {
  }
  try {
    (void)simu::data::validate_cache(path);
  } catch (const simu::Error&) {
  } catch (const c10::Error&) {
  }
  return 0;
}
