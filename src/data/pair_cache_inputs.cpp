// The inputs mode of the pair cache (cond_mode "inputs"): the six condition-input datasets, their
// storage dtypes, value checks, encoding for the writer and decoding for the reader
// (pair_cache_layout.h, pair_cache.h, docs/pair_cache.md).
#include <fmt/ranges.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include "common/error.h"
#include "data/pair_cache_layout.h"

namespace simu::data {

using namespace h5;

const std::vector<std::string>& condition_input_names() {
  static const std::vector<std::string> names{"image", "rgb_image", "mask", "rgb_image_mask", "pointmap", "rgb_pointmap"};
  return names;
}

InputsLayout InputsLayout::storage_named(const std::string& name, int64_t image_size, int64_t pointmap_size) {
  SIMU_CHECK(image_size > 0 && pointmap_size > 0,
             "inputs storage: image and point map sizes must be positive (got {} and {}; a point map kept at the "
             "crop's size cannot be stored)", image_size, pointmap_size);
  InputsLayout l;
  l.image_size = image_size;
  l.pointmap_size = pointmap_size;
  if (name == "exact") return l;
  if (name == "compact") {
    l.image_dtype = torch::kByte;
    l.pointmap_dtype = torch::kFloat16;
    return l;
  }
  fail("inputs storage '{}' is not known (expected 'exact' or 'compact')", name);
}

namespace {

// Index of a condition input by name, or -1.
int64_t input_index(const std::string& name) {
  const auto& names = condition_input_names();
  const auto it = std::find(names.begin(), names.end(), name);
  return it == names.end() ? -1 : it - names.begin();
}

std::string storage_name(torch::ScalarType t) {
  if (t == torch::kByte) return "uint8";
  return dtype_str(t);  // float16 / float32, else an error
}

// Minimum, maximum (over non-NaN values) and whether NaN / Inf occur, in one plain pass.
struct ValueStats {
  float lo = std::numeric_limits<float>::infinity(), hi = -std::numeric_limits<float>::infinity();
  bool nan = false, inf = false;
};
ValueStats value_stats(const float* p, int64_t n) {
  ValueStats s;
  for (int64_t k = 0; k < n; ++k) {
    const float v = p[k];
    if (std::isnan(v)) {
      s.nan = true;
      continue;
    }
    if (std::isinf(v)) s.inf = true;
    s.lo = std::min(s.lo, v);
    s.hi = std::max(s.hi, v);
  }
  return s;
}

}  // namespace

std::string check_condition_input(const std::string& name, const torch::Tensor& value) {
  const int64_t k = input_index(name);
  if (k < 0) return fmt::format("'{}' is not a condition input (expected one of {})", name, fmt::join(condition_input_names(), ", "));
  const auto t = value.to(torch::kCPU, torch::kFloat32).contiguous();
  const auto s = value_stats(t.data_ptr<float>(), t.numel());
  if (layout::is_pointmap_input(static_cast<size_t>(k)))
    return s.inf ? "holds +-Inf (invalid points must be NaN)" : "";
  if (s.nan || s.inf) return "holds NaN or Inf";
  if (t.numel() == 0) return "";
  const bool mask = layout::is_mask_input(static_cast<size_t>(k));
  const float lo = mask ? 0.0f : -0.25f, hi = mask ? 1.0f : 1.25f;
  if (s.lo < lo || s.hi > hi)
    return fmt::format("holds values in [{}, {}], expected [{}, {}]{}", s.lo, s.hi, lo, hi,
                       mask ? "" : " (an image in [0, 1] plus the resize's overshoot)");
  return "";
}

namespace layout {

int64_t input_channels(size_t k) { return is_mask_input(k) ? 1 : 3; }
int64_t input_side(size_t k, const CacheInfo& info) { return info.input_size.at(is_pointmap_input(k) ? 1 : 0); }
bool is_mask_input(size_t k) { return k == 2 || k == 3; }
bool is_pointmap_input(size_t k) { return k == 4 || k == 5; }

float u8_level(uint8_t q) {
  static const std::array<float, 256> table = [] {
    std::array<float, 256> t{};
    const float scale = static_cast<float>(1.0 / 255.0);
    for (int i = 0; i < 256; ++i) t[i] = static_cast<float>(i) * scale;
    return t;
  }();
  return table[q];
}

H5Id storage_mem_type(const std::string& dtype) {
  if (dtype == "uint8") return H5Id(H5Tcopy(H5T_NATIVE_UINT8));
  return float_mem_type(dtype);
}

// Storage dtype name of input k of a cache.
static const std::string& input_dtype(size_t k, const CacheInfo& info) {
  static const std::string u8 = "uint8";
  if (is_mask_input(k)) return u8;
  return is_pointmap_input(k) ? info.pointmap_dtype : info.image_dtype;
}

void open_input_datasets(CacheHandles& h, const std::string& path, int64_t n, bool multi_record) {
  auto& info = h.info;
  h.multi_record = multi_record;
  const auto& names = condition_input_names();
  for (size_t k = 0; k < names.size(); ++k) {
    h.inputs[k] = open_dataset(h.file.get(), names[k].c_str(), path);
    const int64_t side = input_side(k, info);
    const std::vector<int64_t> shape{n, input_channels(k), side, side};
    std::vector<std::string> allowed{"uint8"};
    if (is_pointmap_input(k)) allowed = {"float16", "float32"};
    else if (!is_mask_input(k)) allowed = {"uint8", "float16", "float32"};
    // The second image / point map must share the first one's storage.
    if (k == 1) allowed = {info.image_dtype};
    if (k == 5) allowed = {info.pointmap_dtype};
    const auto dt = check_dataset(h.inputs[k].get(), names[k].c_str(), allowed, shape, path);
    check_record_layout(h.inputs[k].get(), path, names[k], multi_record);
    if (k == 0) info.image_dtype = dt;
    if (k == 4) info.pointmap_dtype = dt;
  }
}

torch::Tensor read_input_rows(const CacheHandles& h, size_t k, int64_t start, int64_t count) {
  const auto& info = h.info;
  const auto& name = condition_input_names()[k];
  const auto& dt = input_dtype(k, info);
  if (dt != "uint8") return read_float_rows(h.inputs[k].get(), dt, start, count, info.path, name, h.multi_record);
  const int64_t side = input_side(k, info);
  auto raw = torch::empty({count, input_channels(k), side, side}, torch::kByte);
  H5Id mt = storage_mem_type(dt);
  read_record_rows(h.inputs[k].get(), mt.get(), start, count, raw.data_ptr(), info.path, name, h.multi_record);
  auto out = torch::empty(raw.sizes(), torch::kFloat32);
  const uint8_t* src = raw.data_ptr<uint8_t>();
  float* dst = out.data_ptr<float>();
  for (int64_t i = 0, n = raw.numel(); i < n; ++i) dst[i] = u8_level(src[i]);
  return out;
}

void create_input_datasets(CacheHandles& h, const InputsLayout& layout, const std::string& path,
                           hsize_t chunk_rows) {
  auto& info = h.info;
  h.multi_record = chunk_rows > 1;
  info.input_size = {layout.image_size, layout.pointmap_size};
  info.image_dtype = storage_name(layout.image_dtype);
  info.pointmap_dtype = storage_name(layout.pointmap_dtype);
  SIMU_CHECK(info.pointmap_dtype != "uint8", "pair cache '{}': point maps are stored as float16 or float32, not uint8", path);
  const auto& names = condition_input_names();
  for (size_t k = 0; k < names.size(); ++k) {
    const auto& dt = input_dtype(k, info);
    H5Id ftype = dt == "uint8" ? H5Id(H5Tcopy(H5T_STD_U8LE)) : dt == "float16" ? make_f16_type() : H5Id(H5Tcopy(H5T_IEEE_F32LE));
    const int64_t side = input_side(k, info);
    const size_t chunk_bytes = chunk_rows * static_cast<size_t>(input_channels(k) * side * side) * H5Tget_size(ftype.get());
    h.inputs[k] = create_rows_dataset(h.file.get(), names[k], ftype.get(), {input_channels(k), side, side}, chunk_rows,
                                      true, path, chunk_rows > 1 ? 2 * chunk_bytes + (1 << 16) : 0);
  }
}

torch::Tensor encode_input(size_t k, const torch::Tensor& value, const CacheInfo& info, const std::string& path,
                           const std::string& id) {
  const auto& name = condition_input_names()[k];
  const int64_t side = input_side(k, info);
  const std::vector<int64_t> want{input_channels(k), side, side};
  if (!value.defined()) fail("pair cache '{}': pair '{}': condition input '{}' is missing", path, id, name);
  auto t = value.dim() == 4 && value.size(0) == 1 ? value[0] : value;
  if (t.sizes().vec() != want || !t.is_floating_point())
    fail("pair cache '{}': pair '{}': condition input '{}' is [{}] {}, expected float [{}]", path, id, name,
         fmt::join(value.sizes(), ", "), c10::toString(value.scalar_type()), fmt::join(want, ", "));
  t = t.detach().to(torch::kCPU, torch::kFloat32).contiguous();
  const auto problem = check_condition_input(name, t);
  if (!problem.empty()) fail("pair cache '{}': pair '{}': condition input '{}' {}", path, id, name, problem);
  const auto& dt = input_dtype(k, info);
  if (dt == "float32") return t;
  if (dt == "float16") {
    auto h = t.to(torch::kFloat16);
    if (torch::isinf(h).any().item<bool>())
      fail("pair cache '{}': pair '{}': condition input '{}' overflows float16 (|x| > 65504)", path, id, name);
    return h.contiguous();
  }
  // uint8: images are rounded (lossy, documented); masks must be exact 8-bit levels.
  auto q = (t.clamp(0, 1) * 255).round().to(torch::kByte).contiguous();
  if (is_mask_input(k)) {
    const float* src = t.data_ptr<float>();
    const uint8_t* lv = q.data_ptr<uint8_t>();
    for (int64_t i = 0, n = t.numel(); i < n; ++i)
      if (u8_level(lv[i]) != src[i])
        fail_hint("give masks read from 8-bit files or binary masks",
                  "pair cache '{}': pair '{}': condition input '{}' holds {} at element {}, not an 8-bit level k/255 "
                  "(masks are stored as uint8)", path, id, name, src[i], i);
  }
  return q;
}

}  // namespace layout
}  // namespace simu::data
