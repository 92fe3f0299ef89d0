#include "data/safetensors_header.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <algorithm>
#include <string_view>

#include "common/error.h"
#include "common/text.h"

namespace simu::data {

size_t safetensors_dtype_size(const std::string& name) {
  static const std::map<std::string, size_t> sizes = {
      {"F64", 8}, {"F32", 4}, {"F16", 2}, {"BF16", 2}, {"I64", 8}, {"I32", 4}, {"I16", 2}, {"I8", 1}, {"U8", 1},
      {"U16", 2}, {"U32", 4}, {"U64", 8}, {"BOOL", 1}, {"F8_E4M3", 1}, {"F8_E5M2", 1}};
  const auto it = sizes.find(name);
  return it == sizes.end() ? 0 : it->second;
}

namespace {

// The 8-byte little-endian length N and the N bytes of JSON after it (an object); n_out = N.
nlohmann::json header_json(const uint8_t* bytes, uint64_t size, const std::string& path, uint64_t& n_out) {
  if (size < 8) fail("{}: truncated safetensors file ({} bytes, the 8-byte header length is missing)", path, size);
  uint64_t n = 0;
  for (int i = 7; i >= 0; --i) n = (n << 8) | bytes[i];
  if (n > size - 8)
    fail("{}: truncated safetensors file: header says {} bytes of JSON, file has {} after it", path, n, size - 8);
  if (n > kMaxSafetensorsHeader)
    fail("{}: safetensors header of {} bytes is larger than the format's limit of {}", path, n, kMaxSafetensorsHeader);
  nlohmann::json header = text::parse_json(
      std::string_view(reinterpret_cast<const char*>(bytes) + 8, static_cast<size_t>(n)), path + " (safetensors header)");
  if (!header.is_object()) fail("{}: safetensors header is a JSON {}, expected an object", path, header.type_name());
  n_out = n;
  return header;
}

// __metadata__: an object of strings.
void read_metadata(const nlohmann::json& m, const std::string& path, std::map<std::string, std::string>& out) {
  if (!m.is_object()) fail("{}: __metadata__ is a JSON {}, expected an object of strings", path, m.type_name());
  for (auto it = m.begin(); it != m.end(); ++it) {
    if (!it->is_string()) fail("{}: __metadata__['{}'] is a JSON {}, expected a string", path, it.key(), it->type_name());
    out[it.key()] = it->get<std::string>();
  }
}

// The shape of tensor t (its dtype known) and the byte count it needs, without overflow.
uint64_t read_shape(const nlohmann::json& sh, const std::string& path, HeaderEntry& t) {
  const std::string& key = t.name;
  if (!sh.is_array() || sh.size() > kMaxSafetensorsRank)
    fail("{}: tensor '{}': shape is {}, expected a list of at most {} non-negative integers", path, key,
         text::excerpt(sh), kMaxSafetensorsRank);
  uint64_t bytes_needed = t.element_size;
  for (const auto& d : sh) {
    if (!d.is_number_integer() || (d.is_number_integer() && !d.is_number_unsigned() && d.get<int64_t>() < 0))
      fail("{}: tensor '{}': shape is {}, expected non-negative integers", path, key, text::excerpt(sh));
    if (d.is_number_unsigned() && d.get<uint64_t>() > static_cast<uint64_t>(INT64_MAX))
      fail("{}: tensor '{}': dimension {} in shape is too large", path, key, d.get<uint64_t>());
    const int64_t v = d.get<int64_t>();
    t.shape.push_back(v);
    if (bytes_needed != 0 && __builtin_mul_overflow(bytes_needed, static_cast<uint64_t>(v), &bytes_needed))
      fail("{}: tensor '{}': shape {} of {} overflows a 64-bit byte count", path, key, text::excerpt(sh), t.dtype);
    if (v == 0) bytes_needed = 0;
  }
  return bytes_needed;
}

// One tensor entry {dtype, shape, data_offsets}; its bytes lie in the data buffer of `buffer` bytes and
// match its shape and dtype.
HeaderEntry read_entry(const std::string& key, const nlohmann::json& e, const std::string& path, uint64_t buffer) {
  if (!e.is_object() || !e.contains("dtype") || !e.contains("shape") || !e.contains("data_offsets"))
    fail("{}: tensor '{}': expected an object with dtype, shape and data_offsets, got {}", path, key, text::excerpt(e));
  HeaderEntry t;
  t.name = key;
  const auto& dt = e["dtype"];
  if (!dt.is_string()) fail("{}: tensor '{}': dtype is {}, expected a string such as \"F32\"", path, key, text::excerpt(dt));
  t.dtype = dt.get<std::string>();
  t.element_size = safetensors_dtype_size(t.dtype);
  if (t.element_size == 0)
    fail("{}: tensor '{}': unknown dtype '{}' (expected F64, F32, F16, BF16, I64, I32, I16, I8, U64, U32, U16, U8, "
         "BOOL, F8_E4M3 or F8_E5M2)",
         path, key, t.dtype);
  const uint64_t bytes_needed = read_shape(e["shape"], path, t);
  const auto& off = e["data_offsets"];
  if (!off.is_array() || off.size() != 2 || !off[0].is_number_unsigned() || !off[1].is_number_unsigned())
    fail("{}: tensor '{}': data_offsets is {}, expected [begin, end] (two non-negative integers)", path, key,
         text::excerpt(off));
  t.begin = off[0].get<uint64_t>();
  t.end = off[1].get<uint64_t>();
  if (t.end < t.begin || t.end > buffer)
    fail("{}: tensor '{}': data_offsets [{}, {}] outside the data buffer of {} bytes (truncated file?)", path, key,
         t.begin, t.end, buffer);
  if (t.end - t.begin != bytes_needed)
    fail("{}: tensor '{}': {} bytes for shape [{}] of {} ({} expected)", path, key, t.end - t.begin,
         fmt::join(t.shape, ", "), t.dtype, bytes_needed);
  return t;
}

// Sorts the tensors into data order and checks that no two non-empty ones share bytes.
void sort_and_check_overlap(std::vector<HeaderEntry>& tensors, const std::string& path) {
  std::stable_sort(tensors.begin(), tensors.end(),
                   [](const HeaderEntry& a, const HeaderEntry& b) { return a.begin < b.begin; });
  uint64_t prev_end = 0;
  const HeaderEntry* prev = nullptr;
  for (const auto& t : tensors) {
    if (t.end == t.begin) continue;
    if (prev && t.begin < prev_end) fail("{}: tensors '{}' and '{}' overlap in the data buffer", path, prev->name, t.name);
    prev_end = t.end;
    prev = &t;
  }
}

}  // namespace

SafeTensorsHeader parse_safetensors_header(const uint8_t* bytes, uint64_t size, const std::string& path) {
  SafeTensorsHeader h;
  uint64_t n = 0;
  const nlohmann::json header = header_json(bytes, size, path, n);
  h.data_start = 8 + n;
  const uint64_t buffer = size - h.data_start;
  for (auto it = header.begin(); it != header.end(); ++it) {
    if (it.key() == "__metadata__")
      read_metadata(*it, path, h.metadata);
    else
      h.tensors.push_back(read_entry(it.key(), *it, path, buffer));
  }
  sort_and_check_overlap(h.tensors, path);
  return h;
}

}  // namespace simu::data
