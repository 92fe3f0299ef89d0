// The safetensors header and tensor table, parsed and checked without torch (the fuzz target and
// SafeTensorsFile share it).
//
// Format: u64 little-endian header length N, N bytes of JSON
// {"name": {"dtype": "F32", "shape": [..], "data_offsets": [begin, end]}, "__metadata__": {..}},
// then the data buffer. Checked before anything is allocated for a tensor: N <= 100 MB (the format's
// limit) and within the file, valid UTF-8 JSON with bounded nesting, every entry's dtype known,
// shape non-negative with at most kMaxRank dimensions and an element count whose byte size does
// not overflow, offsets inside the data buffer and equal to the shape's byte size, no overlaps.
#pragma once

#include <cstddef>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

namespace simu::data {

inline constexpr uint64_t kMaxSafetensorsHeader = 100000000;  // bytes of JSON (the format's limit)
inline constexpr size_t kMaxSafetensorsRank = 64;

// One tensor's entry in the header.
struct HeaderEntry {
  std::string name;
  std::string dtype;            // safetensors name: "F32", "BF16", ...
  size_t element_size = 0;      // bytes per element of dtype
  std::vector<int64_t> shape;
  uint64_t begin = 0, end = 0;  // offsets into the data buffer
};

struct SafeTensorsHeader {
  std::vector<HeaderEntry> tensors;              // in order of their data offsets
  std::map<std::string, std::string> metadata;   // __metadata__
  uint64_t data_start = 0;                       // 8 + N
};

// Bytes per element of a safetensors dtype name; 0 for a name this toolkit does not know.
size_t safetensors_dtype_size(const std::string& name);
// Parses and checks the header of a whole file's bytes. Throws simu::Error "<path>: ..." naming
// the tensor and what was expected.
SafeTensorsHeader parse_safetensors_header(const uint8_t* bytes, uint64_t size, const std::string& path);

}  // namespace simu::data
