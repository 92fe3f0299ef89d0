// HDF5 plumbing of the pair cache: error text, ids, rows, attributes (pair_cache_h5.h).
#include "data/pair_cache_h5.h"

#include <fcntl.h>
#include <unistd.h>

#include <fmt/ranges.h>

#include "common/error.h"

namespace simu::data {

std::recursive_mutex& hdf5_mutex() {
  static std::recursive_mutex m;
  return m;
}

namespace h5 {

namespace {
constexpr int kGzipLevel = 4;
constexpr hssize_t kMaxAttrValues = 64;   // values of an integer root attribute (shapes, version)
constexpr size_t kMaxAttrString = 1 << 16;  // bytes of a fixed-length string root attribute
}  // namespace

// The innermost description of the current HDF5 error stack (then clears it).
std::string h5_error() {
  std::string text;
  H5Ewalk2(
      H5E_DEFAULT, H5E_WALK_UPWARD,  // upward: entry 0 is the innermost (most specific) error
      [](unsigned n, const H5E_error2_t* e, void* data) -> herr_t {
        auto* s = static_cast<std::string*>(data);
        if (n == 0 && e->desc) *s = e->desc;
        return 0;
      },
      &text);
  H5Eclear2(H5E_DEFAULT);
  return text.empty() ? std::string("unknown HDF5 error") : text;
}

// Checks an HDF5 return value / id; on failure throws naming the file and what was being done.
hid_t check_id(hid_t id, const std::string& file, const std::string& what) {
  if (id < 0) fail("pair cache '{}': {}: {}", file, what, h5_error());
  return id;
}
void check_ok(herr_t r, const std::string& file, const std::string& what) {
  if (r < 0) fail("pair cache '{}': {}: {}", file, what, h5_error());
}

// IEEE half precision little-endian (the same definition h5py uses for numpy float16).
H5Id make_f16_type() {
  H5Id t(H5Tcopy(H5T_IEEE_F32LE));
  H5Tset_fields(t.get(), 15, 10, 5, 0, 10);
  H5Tset_size(t.get(), 2);
  H5Tset_ebias(t.get(), 15);
  return t;
}

// Variable-length UTF-8 string type.
H5Id make_vlen_string_type() {
  H5Id t(H5Tcopy(H5T_C_S1));
  H5Tset_size(t.get(), H5T_VARIABLE);
  H5Tset_cset(t.get(), H5T_CSET_UTF8);
  return t;
}

std::string dtype_str(torch::ScalarType t) {
  if (t == torch::kFloat16) return "float16";
  if (t == torch::kFloat32) return "float32";
  fail("pair cache dtype must be float16 or float32, got {}", c10::toString(t));
}

// A readable name of an HDF5 datatype ("float16", "uint8", "string", ...).
std::string type_name(hid_t type) {
  const auto cls = H5Tget_class(type);
  const size_t size = H5Tget_size(type);
  switch (cls) {
    case H5T_FLOAT: return fmt::format("float{}", size * 8);
    case H5T_INTEGER:
      return fmt::format("{}int{}", H5Tget_sign(type) == H5T_SGN_NONE ? "u" : "", size * 8);
    case H5T_STRING: return H5Tis_variable_str(type) > 0 ? "string" : fmt::format("string{}", size);
    default: return fmt::format("hdf5-class-{}", static_cast<int>(cls));
  }
}

std::vector<int64_t> space_dims(hid_t space) {
  const int rank = H5Sget_simple_extent_ndims(space);
  std::vector<hsize_t> d(std::max(rank, 0));
  if (rank > 0) H5Sget_simple_extent_dims(space, d.data(), nullptr);
  return std::vector<int64_t>(d.begin(), d.end());
}

std::vector<int64_t> dataset_dims(hid_t dset) {
  H5Id space(H5Dget_space(dset));
  return space_dims(space.get());
}

namespace {
// The file space of a dataset with rows [start, start+count) of dimension 0 selected (all of the other
// dimensions), and the matching memory space.
struct RowSelection {
  H5Id file_space, mem_space;
};
RowSelection select_rows(hid_t dset, int64_t start, int64_t count, const std::string& file, const std::string& what) {
  RowSelection sel;
  sel.file_space = H5Id(H5Dget_space(dset));
  auto dims = space_dims(sel.file_space.get());
  std::vector<hsize_t> off(dims.size(), 0), cnt(dims.begin(), dims.end());
  off[0] = static_cast<hsize_t>(start);
  cnt[0] = static_cast<hsize_t>(count);
  check_ok(H5Sselect_hyperslab(sel.file_space.get(), H5S_SELECT_SET, off.data(), nullptr, cnt.data(), nullptr), file,
           what);
  sel.mem_space = H5Id(H5Screate_simple(static_cast<int>(cnt.size()), cnt.data(), nullptr));
  return sel;
}
}  // namespace

void read_rows(hid_t dset, hid_t mtype, int64_t start, int64_t count, void* buf, const std::string& file,
               const std::string& name) {
  const RowSelection sel = select_rows(dset, start, count, file,
                                       fmt::format("dataset '{}': select records {}..{}", name, start, start + count - 1));
  if (H5Dread(dset, mtype, sel.mem_space.get(), sel.file_space.get(), H5P_DEFAULT, buf) < 0) {
    const auto why = h5_error();
    if (count == 1) fail("pair cache '{}': record {}: cannot read dataset '{}': {}", file, start, name, why);
    fail("pair cache '{}': records {}..{}: cannot read dataset '{}': {}", file, start, start + count - 1, name, why);
  }
}

void write_rows(hid_t dset, hid_t mtype, int64_t start, int64_t count, const void* buf, const std::string& file,
                const std::string& name) {
  const RowSelection sel = select_rows(dset, start, count, file, "select rows of " + name);
  check_ok(H5Dwrite(dset, mtype, sel.mem_space.get(), sel.file_space.get(), H5P_DEFAULT, buf), file,
           fmt::format("write record {} of dataset '{}'", start, name));
}

// Grows dimension 0 of a dataset to n rows.
void extend_rows(hid_t dset, int64_t n, const std::string& file, const std::string& name) {
  auto dims = dataset_dims(dset);
  std::vector<hsize_t> d(dims.begin(), dims.end());
  d[0] = static_cast<hsize_t>(n);
  check_ok(H5Dset_extent(dset, d.data()), file, "extend dataset " + name);
}

// Creates an extendible dataset [0, row...] with chunks [chunk_rows, row...], optionally shuffle+gzip.
H5Id create_rows_dataset(hid_t file, const std::string& name, hid_t ftype, const std::vector<int64_t>& row,
                         hsize_t chunk_rows, bool compress, const std::string& path) {
  std::vector<hsize_t> dims{0}, maxdims{H5S_UNLIMITED}, chunk{chunk_rows};
  for (auto r : row) {
    dims.push_back(static_cast<hsize_t>(r));
    maxdims.push_back(static_cast<hsize_t>(r));
    chunk.push_back(static_cast<hsize_t>(r));
  }
  H5Id space(check_id(H5Screate_simple(static_cast<int>(dims.size()), dims.data(), maxdims.data()), path,
                      "dataspace of " + name));
  H5Id dcpl(H5Pcreate(H5P_DATASET_CREATE));
  check_ok(H5Pset_chunk(dcpl.get(), static_cast<int>(chunk.size()), chunk.data()), path, "chunking of " + name);
  if (compress) {
    check_ok(H5Pset_shuffle(dcpl.get()), path, "shuffle filter of " + name);
    check_ok(H5Pset_deflate(dcpl.get(), kGzipLevel), path, "gzip filter of " + name);
  }
  return H5Id(check_id(H5Dcreate2(file, name.c_str(), ftype, space.get(), H5P_DEFAULT, dcpl.get(), H5P_DEFAULT),
                       path, "create dataset " + name));
}

namespace {
// One attribute (replaced when it exists).
void write_attr_raw(hid_t obj, const char* name, hid_t ftype, hid_t mtype, hid_t space, const void* buf,
                    const std::string& path) {
  if (H5Aexists(obj, name) > 0) H5Adelete(obj, name);
  H5Id a(check_id(H5Acreate2(obj, name, ftype, space, H5P_DEFAULT, H5P_DEFAULT), path,
                  fmt::format("create attribute {}", name)));
  check_ok(H5Awrite(a.get(), mtype, buf), path, fmt::format("write attribute {}", name));
}
}  // namespace

void write_attr_int(hid_t obj, const char* name, int64_t v, const std::string& path) {
  H5Id space(H5Screate(H5S_SCALAR));
  write_attr_raw(obj, name, H5T_STD_I64LE, H5T_NATIVE_INT64, space.get(), &v, path);
}
void write_attr_ints(hid_t obj, const char* name, const std::vector<int64_t>& v, const std::string& path) {
  hsize_t n = v.size();
  H5Id space(H5Screate_simple(1, &n, nullptr));
  write_attr_raw(obj, name, H5T_STD_I64LE, H5T_NATIVE_INT64, space.get(), v.data(), path);
}
void write_attr_str(hid_t obj, const char* name, const std::string& v, const std::string& path) {
  H5Id space(H5Screate(H5S_SCALAR));
  H5Id t = make_vlen_string_type();
  const char* p = v.c_str();
  write_attr_raw(obj, name, t.get(), t.get(), space.get(), &p, path);
}

// Attribute readers; a missing or ill-typed attribute throws naming the file and attribute.
H5Id open_attr(hid_t obj, const char* name, const std::string& path) {
  if (H5Aexists(obj, name) <= 0)
    fail_hint("is this a pair cache written by PairCacheWriter? see docs/pair_cache.md",
              "pair cache '{}': root attribute '{}' is missing", path, name);
  return H5Id(check_id(H5Aopen(obj, name, H5P_DEFAULT), path, fmt::format("open attribute {}", name)));
}
std::vector<int64_t> read_attr_ints(hid_t obj, const char* name, const std::string& path) {
  H5Id a = open_attr(obj, name, path);
  H5Id t(H5Aget_type(a.get()));
  if (H5Tget_class(t.get()) != H5T_INTEGER)
    fail("pair cache '{}': root attribute '{}' has type {}, expected integer", path, name, type_name(t.get()));
  H5Id space(H5Aget_space(a.get()));
  const hssize_t n = H5Sget_simple_extent_npoints(space.get());
  if (n < 0 || n > kMaxAttrValues)
    fail("pair cache '{}': root attribute '{}' holds {} values, expected at most {}", path, name, n, kMaxAttrValues);
  std::vector<int64_t> v(static_cast<size_t>(std::max<hssize_t>(n, 0)));
  if (!v.empty()) check_ok(H5Aread(a.get(), H5T_NATIVE_INT64, v.data()), path, fmt::format("read attribute {}", name));
  return v;
}
std::string read_attr_str(hid_t obj, const char* name, const std::string& path) {
  H5Id a = open_attr(obj, name, path);
  H5Id t(H5Aget_type(a.get()));
  if (H5Tget_class(t.get()) != H5T_STRING)
    fail("pair cache '{}': root attribute '{}' has type {}, expected string", path, name, type_name(t.get()));
  {
    H5Id space(H5Aget_space(a.get()));
    if (H5Sget_simple_extent_npoints(space.get()) != 1)
      fail("pair cache '{}': root attribute '{}' holds {} values, expected one string", path, name,
           H5Sget_simple_extent_npoints(space.get()));
  }
  if (H5Tis_variable_str(t.get()) > 0) {
    H5Id mt = make_vlen_string_type();
    char* p = nullptr;
    check_ok(H5Aread(a.get(), mt.get(), &p), path, fmt::format("read attribute {}", name));
    std::string s = p ? p : "";
    H5free_memory(p);
    return s;
  }
  const size_t size = H5Tget_size(t.get());
  if (size == 0 || size > kMaxAttrString)
    fail("pair cache '{}': root attribute '{}' is a string of {} bytes, expected 1..{}", path, name, size, kMaxAttrString);
  std::string s(size, '\0');
  H5Id mt(H5Tcopy(H5T_C_S1));
  H5Tset_size(mt.get(), size);
  check_ok(H5Aread(a.get(), mt.get(), s.data()), path, fmt::format("read attribute {}", name));
  s.resize(std::strlen(s.c_str()));
  return s;
}

// Reads n string elements of a dataset starting at start (variable-length or fixed-length strings).
std::vector<std::string> read_strings(hid_t dset, int64_t start, int64_t n, const std::string& path,
                                      const std::string& name) {
  std::vector<std::string> out;
  if (n == 0) return out;
  H5Id ft(H5Dget_type(dset));
  if (H5Tis_variable_str(ft.get()) > 0) {
    H5Id mt = make_vlen_string_type();
    std::vector<char*> ptrs(static_cast<size_t>(n), nullptr);
    read_rows(dset, mt.get(), start, n, ptrs.data(), path, name);
    out.reserve(ptrs.size());
    for (auto* p : ptrs) out.emplace_back(p ? p : "");
    hsize_t cnt = static_cast<hsize_t>(n);
    H5Id ms(H5Screate_simple(1, &cnt, nullptr));
    H5Dvlen_reclaim(mt.get(), ms.get(), H5P_DEFAULT, ptrs.data());
  } else {
    const size_t size = H5Tget_size(ft.get());
    if (size == 0 || size > (1u << 20)) fail("pair cache '{}': dataset '{}' holds strings of {} bytes, expected 1..1 MiB", path, name, size);
    H5Id mt(H5Tcopy(H5T_C_S1));
    H5Tset_size(mt.get(), size);
    std::vector<char> buf(size * static_cast<size_t>(n));
    read_rows(dset, mt.get(), start, n, buf.data(), path, name);
    for (int64_t i = 0; i < n; ++i) {
      const char* p = buf.data() + i * size;
      out.emplace_back(p, strnlen(p, size));
    }
  }
  return out;
}

// Fsyncs a file by path.
void fsync_path(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY);
  if (fd < 0) fail("cannot open '{}' to fsync: {}", path, std::strerror(errno));
  const int r = ::fsync(fd);
  ::close(fd);
  if (r != 0) fail("cannot fsync '{}': {}", path, std::strerror(errno));
}

}  // namespace h5
}  // namespace simu::data
