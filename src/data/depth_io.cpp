#include "data/depth_io.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>

#include "common/error.h"
#include "common/fs.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

namespace simu::data {

namespace {

std::string lower_ext(const std::string& path) {
  auto e = std::filesystem::path(path).extension().string();
  for (auto& c : e) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return e;
}

// Skips spaces in a header string.
void skip_ws(const std::string& s, size_t& i) {
  while (i < s.size() && (s[i] == ' ' || s[i] == '\t' || s[i] == '\n')) ++i;
}

// Parses the Python dict literal of an .npy header: {'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }
void parse_npy_dict(const std::string& path, const std::string& h, NpyHeader& out) {
  auto bad = [&](const std::string& why) {
    fail("{}: malformed .npy header ({}): expected a dict with 'descr', 'fortran_order' and 'shape', got \"{}\"", path,
         why, h.substr(0, 200));
  };
  size_t i = 0;
  skip_ws(h, i);
  if (i >= h.size() || h[i] != '{') bad("no opening brace");
  ++i;
  bool have_descr = false, have_fortran = false, have_shape = false;
  for (;;) {
    skip_ws(h, i);
    if (i < h.size() && h[i] == '}') break;
    if (i >= h.size() || (h[i] != '\'' && h[i] != '"')) bad("a key must be a quoted string");
    const char q = h[i++];
    const size_t k0 = i;
    while (i < h.size() && h[i] != q) ++i;
    if (i >= h.size()) bad("unterminated key");
    const std::string key = h.substr(k0, i - k0);
    ++i;
    skip_ws(h, i);
    if (i >= h.size() || h[i] != ':') bad("missing ':' after '" + key + "'");
    ++i;
    skip_ws(h, i);
    if (key == "descr") {
      if (i >= h.size() || (h[i] != '\'' && h[i] != '"')) bad("descr must be a string (structured dtypes are not supported)");
      const char q2 = h[i++];
      const size_t v0 = i;
      while (i < h.size() && h[i] != q2) ++i;
      if (i >= h.size()) bad("unterminated descr");
      out.descr = h.substr(v0, i - v0);
      ++i;
      have_descr = true;
    } else if (key == "fortran_order") {
      if (h.compare(i, 4, "True") == 0) {
        out.fortran_order = true;
        i += 4;
      } else if (h.compare(i, 5, "False") == 0) {
        out.fortran_order = false;
        i += 5;
      } else {
        bad("fortran_order must be True or False");
      }
      have_fortran = true;
    } else if (key == "shape") {
      if (i >= h.size() || h[i] != '(') bad("shape must be a tuple");
      ++i;
      out.shape.clear();
      for (;;) {
        skip_ws(h, i);
        if (i < h.size() && h[i] == ')') break;
        const size_t d0 = i;
        while (i < h.size() && std::isdigit(static_cast<unsigned char>(h[i]))) ++i;
        if (i == d0) bad("shape entries must be non-negative integers");
        const std::string digits = h.substr(d0, i - d0);
        if (digits.size() > 18) fail("{}: .npy shape entry {} is too large", path, digits);
        out.shape.push_back(std::stoll(digits));
        // numpy writes 'L' suffixes in old Python 2 files.
        if (i < h.size() && h[i] == 'L') ++i;
        skip_ws(h, i);
        if (i < h.size() && h[i] == ',') {
          ++i;
          continue;
        }
        skip_ws(h, i);
        if (i < h.size() && h[i] == ')') break;
        bad("shape tuple is not comma separated");
      }
      ++i;
      have_shape = true;
    } else {
      bad("unknown key '" + key + "'");
    }
    skip_ws(h, i);
    if (i < h.size() && h[i] == ',') ++i;
  }
  if (!have_descr || !have_fortran || !have_shape) bad("a key is missing");
}

// dtype letter + size -> torch dtype as stored in the file (u2 read as int16 bits).
torch::ScalarType npy_storage_dtype(const std::string& path, const std::string& descr, int64_t& item_size,
                                    bool& swap) {
  auto unsupported = [&] {
    fail_hint("save the array as float32/float64/uint8/uint16/int16/int32/int64/bool",
              "{}: .npy dtype '{}' is not supported: expected one of b1, i1, u1, i2, u2, i4, i8, f2, f4, f8 "
              "(with '<', '>', '|' or '=')",
              path, descr);
  };
  if (descr.size() < 3) unsupported();
  const char order = descr[0];
  const char kind = descr[1];
  const std::string size_str = descr.substr(2);
  if (order != '<' && order != '>' && order != '|' && order != '=') unsupported();
  if (size_str != "1" && size_str != "2" && size_str != "4" && size_str != "8") unsupported();
  item_size = std::stoll(size_str);
  swap = order == '>' && item_size > 1;  // this library runs on little-endian hosts (x86-64, aarch64)
  if (order == '|' && item_size > 1) unsupported();
  switch (kind) {
    case 'b':
      if (item_size == 1) return torch::kBool;
      break;
    case 'i':
      if (item_size == 1) return torch::kInt8;
      if (item_size == 2) return torch::kInt16;
      if (item_size == 4) return torch::kInt32;
      if (item_size == 8) return torch::kInt64;
      break;
    case 'u':
      if (item_size == 1) return torch::kUInt8;
      if (item_size == 2) return torch::kInt16;  // converted to int32 after reading
      break;
    case 'f':
      if (item_size == 2) return torch::kHalf;
      if (item_size == 4) return torch::kFloat32;
      if (item_size == 8) return torch::kFloat64;
      break;
    default:
      break;
  }
  unsupported();
  return torch::kFloat32;  // not reached
}

}  // namespace

NpyHeader read_npy_header(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  SIMU_CHECK(f.good(), "{}: cannot open the .npy file", path);
  std::error_code ec;
  const uint64_t file_size = std::filesystem::file_size(path, ec);
  SIMU_CHECK(!ec, "{}: cannot read the file size: {}", path, ec.message());
  char magic[8] = {};
  f.read(magic, 8);
  SIMU_CHECK(f.gcount() == 8 && std::memcmp(magic, "\x93NUMPY", 6) == 0,
             "{}: not a .npy file: expected the magic \\x93NUMPY in its first 6 bytes ({} bytes in the file)", path,
             file_size);
  const int major = static_cast<unsigned char>(magic[6]);
  SIMU_CHECK(major >= 1 && major <= 3, "{}: .npy format version {}.{} is not supported (expected 1.0, 2.0 or 3.0)",
             path, major, static_cast<int>(static_cast<unsigned char>(magic[7])));
  uint64_t header_len = 0;
  const int len_bytes = major == 1 ? 2 : 4;
  unsigned char lb[4] = {};
  f.read(reinterpret_cast<char*>(lb), len_bytes);
  SIMU_CHECK(f.gcount() == len_bytes, "{}: truncated .npy file: the header length is cut off", path);
  for (int k = len_bytes - 1; k >= 0; --k) header_len = (header_len << 8) | lb[k];
  const uint64_t prefix = 8 + static_cast<uint64_t>(len_bytes);
  SIMU_CHECK(prefix + header_len <= file_size,
             "{}: truncated .npy file: the header declares {} bytes but the file has {} bytes in all", path, header_len,
             file_size);
  std::string header(static_cast<size_t>(header_len), '\0');
  f.read(header.data(), static_cast<std::streamsize>(header_len));
  SIMU_CHECK(static_cast<uint64_t>(f.gcount()) == header_len, "{}: truncated .npy header", path);
  NpyHeader out;
  parse_npy_dict(path, header, out);
  out.data_offset = prefix + header_len;
  bool swap = false;
  npy_storage_dtype(path, out.descr, out.item_size, swap);
  // Byte count of the declared shape, with overflow checks, against what the file holds.
  uint64_t count = 1;
  for (int64_t d : out.shape) {
    SIMU_CHECK(d >= 0, "{}: negative .npy dimension {}", path, d);
    SIMU_CHECK(d == 0 || count <= std::numeric_limits<uint64_t>::max() / static_cast<uint64_t>(d),
               "{}: .npy shape ({}) is too large: its element count overflows 64 bits", path, fmt::join(out.shape, ", "));
    count *= static_cast<uint64_t>(d);
  }
  SIMU_CHECK(count <= std::numeric_limits<uint64_t>::max() / static_cast<uint64_t>(out.item_size),
             "{}: .npy shape ({}) of dtype {} is too large: its byte count overflows 64 bits", path,
             fmt::join(out.shape, ", "), out.descr);
  const uint64_t bytes = count * static_cast<uint64_t>(out.item_size);
  const uint64_t have = file_size - out.data_offset;
  SIMU_CHECK(bytes == have,
             "{}: .npy header declares shape ({}) of dtype {} = {} data bytes, but the file holds {} bytes after its "
             "header ({})",
             path, fmt::join(out.shape, ", "), out.descr, bytes, have, bytes > have ? "truncated" : "trailing data");
  return out;
}

torch::Tensor read_npy(const std::string& path) {
  const NpyHeader h = read_npy_header(path);  // sizes checked against the file before allocating
  int64_t item_size = 0;
  bool swap = false;
  const auto dtype = npy_storage_dtype(path, h.descr, item_size, swap);
  int64_t count = 1;
  for (int64_t d : h.shape) count *= d;
  auto raw = torch::empty({count * item_size}, torch::kUInt8);
  std::ifstream f(path, std::ios::binary);
  SIMU_CHECK(f.good(), "{}: cannot open the .npy file", path);
  f.seekg(static_cast<std::streamoff>(h.data_offset));
  f.read(reinterpret_cast<char*>(raw.data_ptr<uint8_t>()), static_cast<std::streamsize>(raw.numel()));
  SIMU_CHECK(f.gcount() == raw.numel(), "{}: truncated .npy data: read {} of {} bytes", path, f.gcount(), raw.numel());
  if (swap) {
    uint8_t* p = raw.data_ptr<uint8_t>();
    for (int64_t e = 0; e < count; ++e) std::reverse(p + e * item_size, p + (e + 1) * item_size);
  }
  // Fortran order: the bytes are the C-order array of the reversed shape; transpose back.
  std::vector<int64_t> shape = h.shape;
  if (h.fortran_order) std::reverse(shape.begin(), shape.end());
  auto t = raw.view(dtype).reshape(shape);
  if (h.fortran_order && t.dim() > 1) {
    std::vector<int64_t> perm(static_cast<size_t>(t.dim()));
    for (int64_t k = 0; k < t.dim(); ++k) perm[static_cast<size_t>(k)] = t.dim() - 1 - k;
    t = t.permute(perm).contiguous();
  }
  if (h.descr.substr(1) == "u2") t = t.to(torch::kInt32).bitwise_and(0xFFFF);
  return t;
}

void write_npy(const std::string& path, const torch::Tensor& tensor) {
  const auto t = tensor.detach().to(torch::kCPU).contiguous();
  std::string descr;
  switch (t.scalar_type()) {
    case torch::kBool: descr = "|b1"; break;
    case torch::kUInt8: descr = "|u1"; break;
    case torch::kInt8: descr = "|i1"; break;
    case torch::kInt16: descr = "<i2"; break;
    case torch::kInt32: descr = "<i4"; break;
    case torch::kInt64: descr = "<i8"; break;
    case torch::kHalf: descr = "<f2"; break;
    case torch::kFloat32: descr = "<f4"; break;
    case torch::kFloat64: descr = "<f8"; break;
    default: fail("{}: cannot write dtype {} as .npy", path, c10::toString(t.scalar_type()));
  }
  // Python tuple syntax: (), (5,), (2, 3).
  std::string shape;
  for (int64_t k = 0; k < t.dim(); ++k) shape += (k ? ", " : "") + std::to_string(t.size(k));
  if (t.dim() == 1) shape += ",";
  std::string header = fmt::format("{{'descr': '{}', 'fortran_order': False, 'shape': ({}), }}", descr, shape);
  // Pad with spaces so that magic + length + header + '\n' is a multiple of 64 bytes.
  const size_t total = 10 + header.size() + 1;
  header.append((64 - total % 64) % 64, ' ');
  header.push_back('\n');
  std::string bytes = "\x93NUMPY";
  bytes.push_back('\x01');
  bytes.push_back('\x00');
  bytes.push_back(static_cast<char>(header.size() & 0xFF));
  bytes.push_back(static_cast<char>((header.size() >> 8) & 0xFF));
  bytes += header;
  bytes.append(static_cast<const char*>(t.data_ptr()), static_cast<size_t>(t.numel() * t.element_size()));
  fs::atomic_write(path, bytes);
}

Intrinsics intrinsics_from_json(const nlohmann::json& j, const std::string& what) {
  const std::string expected =
      "expected {\"fx\", \"fy\", \"cx\", \"cy\"} or a 3x3 matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] "
      "(bare, or under \"K\" / \"intrinsics\" / \"camera_matrix\")";
  auto number = [&](const nlohmann::json& v, const std::string& key) {
    SIMU_CHECK(v.is_number(), "{}: '{}' must be a number, got {} ({})", what, key, v.dump(), expected);
    return v.get<double>();
  };
  Intrinsics K;
  const nlohmann::json* matrix = nullptr;
  if (j.is_object()) {
    if (j.contains("fx") || j.contains("fy") || j.contains("cx") || j.contains("cy")) {
      for (const char* k : {"fx", "fy", "cx", "cy"})
        SIMU_CHECK(j.contains(k), "{}: key '{}' is missing ({})", what, k, expected);
      K = {number(j["fx"], "fx"), number(j["fy"], "fy"), number(j["cx"], "cx"), number(j["cy"], "cy")};
    } else {
      for (const char* k : {"K", "intrinsics", "camera_matrix"})
        if (j.contains(k)) {
          matrix = &j[k];
          break;
        }
      SIMU_CHECK(matrix, "{}: no intrinsics found ({})", what, expected);
    }
  } else if (j.is_array()) {
    matrix = &j;
  } else {
    fail("{}: intrinsics must be a JSON object or array ({})", what, expected);
  }
  if (matrix) {
    // 3 rows of 3, or 9 numbers row-major.
    std::vector<double> m;
    const auto& a = *matrix;
    SIMU_CHECK(a.is_array(), "{}: the intrinsics matrix must be an array ({})", what, expected);
    if (a.size() == 3 && a[0].is_array()) {
      for (size_t r = 0; r < 3; ++r) {
        SIMU_CHECK(a[r].is_array() && a[r].size() == 3, "{}: K row {} must have 3 numbers ({})", what, r, expected);
        for (size_t c = 0; c < 3; ++c) m.push_back(number(a[r][c], fmt::format("K[{}][{}]", r, c)));
      }
    } else {
      SIMU_CHECK(a.size() == 9, "{}: K must be 3x3 or 9 numbers, got {} entries ({})", what, a.size(), expected);
      for (size_t k = 0; k < 9; ++k) m.push_back(number(a[k], fmt::format("K[{}]", k)));
    }
    SIMU_CHECK(m[1] == 0 && m[3] == 0 && m[6] == 0 && m[7] == 0 && m[8] == 1,
               "{}: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew, last row 0 0 1), got [{}]", what,
               fmt::join(m, ", "));
    K = {m[0], m[4], m[2], m[5]};
  }
  SIMU_CHECK(std::isfinite(K.fx) && std::isfinite(K.fy) && std::isfinite(K.cx) && std::isfinite(K.cy) && K.fx > 0 &&
                 K.fy > 0,
             "{}: intrinsics must be finite with fx, fy > 0, got fx {} fy {} cx {} cy {}", what, K.fx, K.fy, K.cx, K.cy);
  return K;
}

Intrinsics read_intrinsics_json(const std::string& path) {
  const std::string text = fs::read_file(path);
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(text);
  } catch (const std::exception& e) {
    fail("{}: not valid JSON: {}", path, e.what());
  }
  return intrinsics_from_json(j, path);
}

namespace {
#ifdef SIMU_HAVE_OPENCV
cv::Mat imread_checked(const std::string& path, int flags, const std::string& what) {
  SIMU_CHECK(std::filesystem::exists(path), "{}: {} file not found", path, what);
  if (lower_ext(path) == ".exr") ::setenv("OPENCV_IO_ENABLE_OPENEXR", "1", /*overwrite=*/0);
  cv::Mat m;
  try {
    m = cv::imread(path, flags);
  } catch (const cv::Exception& e) {
    fail("{}: cannot read the {} ({})", path, what, e.what());
  }
  if (m.empty() && lower_ext(path) == ".exr")
    fail_hint("convert it to .npy (float32 metres) or a 16-bit PNG (millimetres)",
              "{}: cannot read the {}: OpenCV could not decode this EXR (built without OpenEXR, or "
              "OPENCV_IO_ENABLE_OPENEXR=0 in the environment)",
              path, what);
  SIMU_CHECK(!m.empty(), "{}: cannot read the {} (not an image OpenCV can decode)", path, what);
  return m;
}
#endif

}  // namespace

torch::Tensor clean_depth(torch::Tensor z) {
  z = z.to(torch::kFloat32);
  return torch::where(torch::isfinite(z) & (z > 0), z, torch::full_like(z, NAN));
}

torch::Tensor read_depth(const std::string& path) {
  const std::string ext = lower_ext(path);
  // A missing file of a depth format is "not found" whatever this build reads (an image format in a
  // build without OpenCV included); an unknown extension is reported as such below.
  const bool depth_format = ext == ".npy" || ext == ".png" || ext == ".tif" || ext == ".tiff" || ext == ".exr";
  SIMU_CHECK(!depth_format || std::filesystem::exists(path), "{}: depth file not found", path);
  if (ext == ".npy") {
    auto t = read_npy(path);
    if (t.dim() == 3 && t.size(2) == 1) t = t.squeeze(2);
    if (t.dim() == 3 && t.size(0) == 1) t = t.squeeze(0);
    SIMU_CHECK(t.dim() == 2, "{}: a depth .npy must have shape [H, W] (or [H, W, 1], [1, H, W]), got {}{}", path,
               t.sizes(), t.dim() == 3 && t.size(2) == 3 ? " (a point map? pass it as --pointmap)" : "");
    if (t.scalar_type() == torch::kInt32 || t.scalar_type() == torch::kInt16) {
      SIMU_CHECK(read_npy_header(path).descr.substr(1) == "u2",
                 "{}: integer depth must be uint16 millimetres, got dtype {}", path, read_npy_header(path).descr);
      return clean_depth(t.to(torch::kFloat64) * 1e-3);
    }
    SIMU_CHECK(t.is_floating_point(), "{}: depth .npy must be float (metres) or uint16 (millimetres), got {}", path,
               read_npy_header(path).descr);
    return clean_depth(t);
  }
#ifdef SIMU_HAVE_OPENCV
  if (ext == ".png" || ext == ".tif" || ext == ".tiff" || ext == ".exr") {
    cv::Mat m = imread_checked(path, cv::IMREAD_UNCHANGED, "depth image");
    SIMU_CHECK(m.channels() == 1 || ext == ".exr", "{}: depth image has {} channels, expected 1", path, m.channels());
    if (m.channels() > 1) {
      std::vector<cv::Mat> ch;
      cv::split(m, ch);
      m = ch[0];
    }
    cv::Mat f;
    if (m.depth() == CV_16U) {
      m.convertTo(f, CV_32F, 1e-3);  // millimetres -> metres
    } else if (m.depth() == CV_32F || m.depth() == CV_64F) {
      SIMU_CHECK(ext == ".exr" || ext == ".tif" || ext == ".tiff", "{}: unexpected float PNG", path);
      m.convertTo(f, CV_32F);  // metres
    } else {
      fail_hint("write depth as a 16-bit PNG in millimetres, a float32 .npy / .exr in metres",
                "{}: depth image must be 16-bit (millimetres) or float (metres), got an {}-bit integer image", path,
                m.depth() == CV_8U || m.depth() == CV_8S ? 8 : 32);
    }
    auto z = torch::from_blob(f.ptr<float>(), {f.rows, f.cols}, {static_cast<int64_t>(f.step[0] / sizeof(float)), 1},
                              torch::kFloat32)
                 .clone();
    return clean_depth(z);
  }
#endif
  fail_hint("use .npy (float metres or uint16 mm), .png (16-bit mm) or .exr (float metres)",
            "{}: unsupported depth file extension '{}'{}", path, ext,
#ifdef SIMU_HAVE_OPENCV
            ""
#else
            " (this build has no OpenCV: only .npy)"
#endif
  );
}

torch::Tensor read_pointmap(const std::string& path) {
  SIMU_CHECK(lower_ext(path) == ".npy", "{}: a point map must be an .npy array [H, W, 3] (MoGe's points)", path);
  SIMU_CHECK(std::filesystem::exists(path), "{}: point map file not found", path);
  auto t = read_npy(path);
  SIMU_CHECK(t.dim() == 3 && t.size(2) == 3, "{}: a point map must have shape [H, W, 3] (OpenCV camera x, y, z), got {}",
             path, t.sizes());
  SIMU_CHECK(t.is_floating_point(), "{}: a point map must be float32 or float64, got {}", path,
             read_npy_header(path).descr);
  return t.to(torch::kFloat32).contiguous();
}

torch::Tensor unproject_depth(const torch::Tensor& depth, const Intrinsics& K) {
  SIMU_CHECK(depth.dim() == 2, "unproject_depth: depth must be [H, W], got {}", depth.sizes());
  const auto z = clean_depth(depth.to(torch::kCPU));
  const int64_t h = z.size(0), w = z.size(1);
  const auto v = torch::arange(h, torch::kFloat64).unsqueeze(1).expand({h, w});
  const auto u = torch::arange(w, torch::kFloat64).unsqueeze(0).expand({h, w});
  const auto z64 = z.to(torch::kFloat64);
  const auto x = (u - K.cx) / K.fx * z64;
  const auto y = (v - K.cy) / K.fy * z64;
  return torch::stack({x, y, z64}, -1).to(torch::kFloat32);  // [H, W, 3]
}

Intrinsics estimate_intrinsics(const torch::Tensor& pointmap, const std::string& what) {
  SIMU_CHECK(pointmap.dim() == 3 && pointmap.size(2) == 3, "{}: a point map must be [H, W, 3], got {}", what,
             pointmap.sizes());
  const auto p = pointmap.to(torch::kCPU, torch::kFloat64);
  const int64_t h = p.size(0), w = p.size(1);
  const auto x = p.select(2, 0), y = p.select(2, 1), z = p.select(2, 2);
  const auto ok = torch::isfinite(p).all(-1) & (z > 0);
  const int64_t n = ok.sum().item<int64_t>();
  SIMU_CHECK(n >= 16, "{}: only {} valid points: cannot fit intrinsics (pass --intrinsics)", what, n);
  const auto v = torch::arange(h, torch::kFloat64).unsqueeze(1).expand({h, w}).masked_select(ok);
  const auto u = torch::arange(w, torch::kFloat64).unsqueeze(0).expand({h, w}).masked_select(ok);
  // One-dimensional least squares per axis: pixel = f * ratio + c.
  auto fit = [&](const torch::Tensor& ratio, const torch::Tensor& pix, const char* axis) {
    const double rm = ratio.mean().item<double>(), pm = pix.mean().item<double>();
    const double var = (ratio - rm).pow(2).sum().item<double>();
    SIMU_CHECK(var > 1e-12, "{}: the points have no spread along {}: cannot fit intrinsics (pass --intrinsics)", what,
               axis);
    const double f = ((ratio - rm) * (pix - pm)).sum().item<double>() / var;
    return std::pair<double, double>{f, pm - f * rm};
  };
  const auto [fx, cx] = fit(x.masked_select(ok) / z.masked_select(ok), u, "x");
  const auto [fy, cy] = fit(y.masked_select(ok) / z.masked_select(ok), v, "y");
  SIMU_CHECK(std::isfinite(fx) && std::isfinite(fy) && fx > 0 && fy > 0,
             "{}: fitted intrinsics are not a camera (fx {} fy {}): is the point map in the OpenCV frame?", what, fx, fy);
  return {fx, fy, cx, cy};
}

torch::Tensor read_label_image(const std::string& path) {
#ifdef SIMU_HAVE_OPENCV
  cv::Mat m = imread_checked(path, cv::IMREAD_UNCHANGED, "label image");
  SIMU_CHECK(m.channels() == 1, "{}: a label image must have one channel (0 = background, k = object k), got {}", path,
             m.channels());
  cv::Mat i32;
  SIMU_CHECK(m.depth() == CV_8U || m.depth() == CV_16U,
             "{}: a label image must be 8- or 16-bit unsigned (0 = background, k = object k)", path);
  m.convertTo(i32, CV_32S);
  return torch::from_blob(i32.ptr<int32_t>(), {i32.rows, i32.cols}, {static_cast<int64_t>(i32.step[0] / 4), 1},
                          torch::kInt32)
      .to(torch::kInt64);
#else
  fail("{}: reading label images needs OpenCV (built with SIMU_WITH_OPENCV=OFF)", path);
#endif
}

}  // namespace simu::data
