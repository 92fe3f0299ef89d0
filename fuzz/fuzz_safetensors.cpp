// libFuzzer target: a safetensors file's header and tensor table (what SafeTensorsFile::open checks
// before it maps a tensor). Input: the whole file's bytes.
#include <cstdint>
#include <cstdlib>

#include "common/error.h"
#include "data/safetensors_header.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  try {
    const auto h = simu::data::parse_safetensors_header(data, size, "fuzz.safetensors");
    // The table's promises: every tensor lies inside the file, and its bytes can be touched.
    uint64_t sum = 0;
    for (const auto& t : h.tensors) {
      if (h.data_start + t.end > size) std::abort();
      for (uint64_t k = t.begin; k < t.end; k += 4096) sum += data[h.data_start + k];
    }
    (void)sum;
  } catch (const simu::Error&) {
    // A clean, named error is the expected outcome for malformed input.
  }
  return 0;
}
