// Pair cache on the HDF5 C API: layout helpers, writer, reader, validator, synthetic maker, stream.
#include "data/pair_cache.h"

#include <fcntl.h>
#include <hdf5.h>
#include <unistd.h>

#include <fmt/ranges.h>

#include <algorithm>
#include <poll.h>
#include <sys/wait.h>

#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <limits>
#include <map>
#include <numeric>
#include <random>

#include "common/error.h"
#include "common/random.h"
#include "common/fs.h"

namespace simu::data {

namespace {

namespace stdfs = std::filesystem;

constexpr const char* kFormat = "simu.pair_cache";
constexpr const char* kDefaultCreatedBy = "simuscene_resampler PairCacheWriter";
constexpr int kGzipLevel = 4;
constexpr hsize_t kScalarChunk = 1024;  // rows per chunk of the per-pair scalar datasets
constexpr hssize_t kMaxAttrValues = 64;   // values of an integer root attribute (shapes, version)
constexpr size_t kMaxAttrString = 1 << 16;  // bytes of a fixed-length string root attribute
// Deflate expands at most ~1032:1; a dataset cannot hold more decoded bytes than this many times
// the file's size (sizes above that come from a corrupt header, and are refused before allocating).
constexpr uint64_t kMaxExpansion = 1100;

// ---------------------------------------------------------------------------------------------
// HDF5 plumbing: the global lock, error text, RAII ids.

// Locks the global HDF5 mutex and silences HDF5's own error printing (we report errors ourselves).
struct H5Lock {
  std::lock_guard<std::recursive_mutex> lock{hdf5_mutex()};
  H5Lock() { H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr); }
};

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

// Owns one HDF5 id and closes it with the function of its type.
class H5Id {
 public:
  H5Id() = default;
  explicit H5Id(hid_t id) : id_(id) {}
  H5Id(const H5Id&) = delete;
  H5Id& operator=(const H5Id&) = delete;
  H5Id(H5Id&& o) noexcept : id_(o.id_) { o.id_ = -1; }
  H5Id& operator=(H5Id&& o) noexcept {
    if (this != &o) {
      reset();
      id_ = o.id_;
      o.id_ = -1;
    }
    return *this;
  }
  ~H5Id() { reset(); }
  hid_t get() const { return id_; }
  bool valid() const { return id_ >= 0; }
  // Closes the id; returns false when the close failed.
  bool reset() {
    if (id_ < 0) return true;
    herr_t r = 0;
    switch (H5Iget_type(id_)) {
      case H5I_FILE: r = H5Fclose(id_); break;
      case H5I_DATASET: r = H5Dclose(id_); break;
      case H5I_DATASPACE: r = H5Sclose(id_); break;
      case H5I_DATATYPE: r = H5Tclose(id_); break;
      case H5I_ATTR: r = H5Aclose(id_); break;
      case H5I_GROUP: r = H5Gclose(id_); break;
      case H5I_GENPROP_LST: r = H5Pclose(id_); break;
      default: r = H5Idec_ref(id_) < 0 ? -1 : 0; break;
    }
    id_ = -1;
    return r >= 0;
  }

 private:
  hid_t id_ = -1;
};

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

// Selects rows [start, start+count) of dimension 0 (all of the other dimensions) and reads them
// into buf (memory type mtype). Throws naming file, dataset and the record range.
void read_rows(hid_t dset, hid_t mtype, int64_t start, int64_t count, void* buf, const std::string& file,
               const std::string& name) {
  H5Id fspace(H5Dget_space(dset));
  auto dims = space_dims(fspace.get());
  std::vector<hsize_t> off(dims.size(), 0), cnt(dims.begin(), dims.end());
  off[0] = static_cast<hsize_t>(start);
  cnt[0] = static_cast<hsize_t>(count);
  check_ok(H5Sselect_hyperslab(fspace.get(), H5S_SELECT_SET, off.data(), nullptr, cnt.data(), nullptr), file,
           fmt::format("dataset '{}': select records {}..{}", name, start, start + count - 1));
  H5Id mspace(H5Screate_simple(static_cast<int>(cnt.size()), cnt.data(), nullptr));
  if (H5Dread(dset, mtype, mspace.get(), fspace.get(), H5P_DEFAULT, buf) < 0) {
    const auto why = h5_error();
    if (count == 1) fail("pair cache '{}': record {}: cannot read dataset '{}': {}", file, start, name, why);
    fail("pair cache '{}': records {}..{}: cannot read dataset '{}': {}", file, start, start + count - 1, name, why);
  }
}

// Writes rows [start, start+count) of dimension 0 from buf.
void write_rows(hid_t dset, hid_t mtype, int64_t start, int64_t count, const void* buf, const std::string& file,
                const std::string& name) {
  H5Id fspace(H5Dget_space(dset));
  auto dims = space_dims(fspace.get());
  std::vector<hsize_t> off(dims.size(), 0), cnt(dims.begin(), dims.end());
  off[0] = static_cast<hsize_t>(start);
  cnt[0] = static_cast<hsize_t>(count);
  check_ok(H5Sselect_hyperslab(fspace.get(), H5S_SELECT_SET, off.data(), nullptr, cnt.data(), nullptr), file,
           "select rows of " + name);
  H5Id mspace(H5Screate_simple(static_cast<int>(cnt.size()), cnt.data(), nullptr));
  check_ok(H5Dwrite(dset, mtype, mspace.get(), fspace.get(), H5P_DEFAULT, buf), file,
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

// Attribute writers (scalar int64, int64 vector, variable-length UTF-8 string); replace existing ones.
void write_attr_raw(hid_t obj, const char* name, hid_t ftype, hid_t mtype, hid_t space, const void* buf,
                    const std::string& path) {
  if (H5Aexists(obj, name) > 0) H5Adelete(obj, name);
  H5Id a(check_id(H5Acreate2(obj, name, ftype, space, H5P_DEFAULT, H5P_DEFAULT), path,
                  fmt::format("create attribute {}", name)));
  check_ok(H5Awrite(a.get(), mtype, buf), path, fmt::format("write attribute {}", name));
}
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

// Checks a float tensor's shape for the writer, naming the record.
void expect_shape(const torch::Tensor& t, const std::vector<int64_t>& want, const std::string& path,
                  const std::string& id, const char* what) {
  if (!t.defined()) fail("pair cache '{}': pair '{}': {} is missing", path, id, what);
  if (t.sizes().vec() != want)
    fail("pair cache '{}': pair '{}': {} has shape [{}], expected [{}]", path, id, what, fmt::join(t.sizes(), ", "),
         fmt::join(want, ", "));
  if (!t.is_floating_point()) fail("pair cache '{}': pair '{}': {} has dtype {}, expected a float tensor", path, id, what,
                                   c10::toString(t.scalar_type()));
  if (!torch::isfinite(t).all().item<bool>())
    fail("pair cache '{}': pair '{}': {} holds NaN or Inf", path, id, what);
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Small public helpers.

std::recursive_mutex& hdf5_mutex() {
  static std::recursive_mutex m;
  return m;
}

std::string kind_name(PairKind kind) {
  return kind == PairKind::OcclusionCompletion ? "occlusion_completion" : "clean_preservation";
}

float default_weight(PairKind kind) { return kind == PairKind::OcclusionCompletion ? 1.0f : 0.1f; }

// ---------------------------------------------------------------------------------------------
// Structure checks shared by the reader and the writer's resume.

namespace {

// Open datasets of a cache and its info; ids are closed under the HDF5 lock by the owner.
struct CacheHandles {
  H5Id file;
  H5Id latent_pos, latent_neg, cond, cond_len, kind, weight, id;
  CacheInfo info;
  bool half = false;  // latents/cond stored as float16

  ~CacheHandles() { close(); }
  void close() {
    std::lock_guard<std::recursive_mutex> lock(hdf5_mutex());
    for (H5Id* d : {&latent_pos, &latent_neg, &cond, &cond_len, &kind, &weight, &id}) d->reset();
    file.reset();
  }
};

// File access properties of every read-only open. Readers skip HDF5's flock: many ranks read one
// file, often on network file systems where flock fails, and writers never modify a file in place
// (they rename a finished temporary over it). All read-only opens must agree on this flag.
H5Id reader_fapl() {
  H5Id fapl(H5Pcreate(H5P_FILE_ACCESS));
#if H5_VERSION_GE(1, 10, 7)
  H5Pset_file_locking(fapl.get(), false, true);
#endif
  return fapl;
}

// Opens a dataset that must exist, naming the file if it does not.
H5Id open_dataset(hid_t file, const char* name, const std::string& path) {
  if (H5Lexists(file, name, H5P_DEFAULT) <= 0)
    fail_hint("the file is incomplete or not a pair cache; see docs/pair_cache.md",
              "pair cache '{}': dataset '{}' is missing", path, name);
  return H5Id(check_id(H5Dopen2(file, name, H5P_DEFAULT), path, fmt::format("open dataset '{}'", name)));
}

// Checks a dataset's dtype name and shape against the expected ones.
std::string check_dataset(hid_t dset, const char* name, const std::vector<std::string>& dtypes,
                          const std::vector<int64_t>& shape, const std::string& path) {
  H5Id t(H5Dget_type(dset));
  const std::string dt = type_name(t.get());
  if (std::find(dtypes.begin(), dtypes.end(), dt) == dtypes.end())
    fail("pair cache '{}': dataset '{}' has dtype {}, expected {}", path, name, dt, fmt::join(dtypes, " or "));
  const auto got = dataset_dims(dset);
  if (got != shape)
    fail("pair cache '{}': dataset '{}' has shape [{}], expected [{}]", path, name, fmt::join(got, ", "),
         fmt::join(shape, ", "));
  return dt;
}

// Opens a file (read-only or read-write) and checks attributes and every dataset.
void open_cache(CacheHandles& h, const std::string& path, bool writable) {
  H5Lock lock;
  if (!stdfs::exists(path)) fail("pair cache '{}' does not exist", path);
  if (H5Fis_hdf5(path.c_str()) <= 0) {
    H5Eclear2(H5E_DEFAULT);
    fail_hint("the file may be truncated or corrupt; recreate it or restore a copy",
              "pair cache '{}' is not a readable HDF5 file", path);
  }
  H5Id fapl = writable ? H5Id(H5Pcreate(H5P_FILE_ACCESS)) : reader_fapl();
  hid_t f = H5Fopen(path.c_str(), writable ? H5F_ACC_RDWR : H5F_ACC_RDONLY, fapl.get());
  if (f < 0)
    fail_hint("the file may be truncated (an interrupted copy?) or corrupt; recreate it or restore a copy",
              "pair cache '{}' cannot be opened: {}", path, h5_error());
  h.file = H5Id(f);
  auto& info = h.info;
  info.path = path;
  // Root attributes.
  const hid_t root = h.file.get();
  if (H5Aexists(root, "format") > 0) {
    const auto fmt_name = read_attr_str(root, "format", path);
    if (fmt_name != kFormat) fail("pair cache '{}': attribute format is '{}', expected '{}'", path, fmt_name, kFormat);
  }
  const auto version = read_attr_ints(root, "schema_version", path);
  if (version.size() != 1) fail("pair cache '{}': attribute schema_version must be one integer", path);
  info.schema_version = static_cast<int>(version[0]);
  if (info.schema_version != kPairCacheSchemaVersion)
    fail_hint("rebuild the cache with this toolkit's writer",
              "pair cache '{}': schema_version {} is not supported (this build reads version {})", path,
              info.schema_version, kPairCacheSchemaVersion);
  info.latent_shape = read_attr_ints(root, "latent_shape", path);
  info.cond_shape = read_attr_ints(root, "cond_shape", path);
  info.cond_mode = read_attr_str(root, "cond_mode", path);
  info.created_by = read_attr_str(root, "created_by", path);
  if (info.latent_shape.size() != 2 || info.latent_shape[0] <= 0 || info.latent_shape[1] <= 0)
    fail("pair cache '{}': attribute latent_shape is [{}], expected [T, C] with T, C > 0", path,
         fmt::join(info.latent_shape, ", "));
  if (info.cond_mode == "inputs")
    fail_hint("write condition tokens (cond_mode tokens) for now",
              "pair cache '{}': cond_mode 'inputs' is reserved in schema 1 but not implemented yet", path);
  if (info.cond_mode != "tokens")
    fail("pair cache '{}': attribute cond_mode is '{}', expected 'tokens'", path, info.cond_mode);
  if (info.cond_shape.size() != 2 || info.cond_shape[0] <= 0 || info.cond_shape[1] <= 0)
    fail("pair cache '{}': attribute cond_shape is [{}], expected [L, Cc] with L, Cc > 0", path,
         fmt::join(info.cond_shape, ", "));
  // Datasets: presence first (so a missing one is named), then dtypes and shapes.
  h.latent_pos = open_dataset(root, "latent_pos", path);
  h.latent_neg = open_dataset(root, "latent_neg", path);
  h.cond = open_dataset(root, "cond", path);
  h.cond_len = open_dataset(root, "cond_len", path);
  h.kind = open_dataset(root, "kind", path);
  h.weight = open_dataset(root, "weight", path);
  h.id = open_dataset(root, "id", path);
  const auto pos_dims = dataset_dims(h.latent_pos.get());
  if (pos_dims.size() != 3)
    fail("pair cache '{}': dataset 'latent_pos' has shape [{}], expected [N, {}, {}]", path, fmt::join(pos_dims, ", "),
         info.latent_shape[0], info.latent_shape[1]);
  const int64_t n = pos_dims[0];
  info.size = n;
  // Sizes from the file's header are checked against the file's length before anything is
  // allocated for them: every pair stores at least its id (one byte or more), and one record's
  // latents or condition cannot decode to more than kMaxExpansion times the file.
  {
    std::error_code ec;
    const uint64_t file_bytes = stdfs::file_size(path, ec);
    if (!ec && static_cast<uint64_t>(n) > file_bytes)
      fail_hint("the file is damaged or not written by this toolkit; rebuild it",
                "pair cache '{}': dataset 'latent_pos' declares {} records, more than a file of {} bytes can hold",
                path, n, file_bytes);
    const uint64_t limit = std::max<uint64_t>(uint64_t{1} << 20, kMaxExpansion * (ec ? 0 : file_bytes));
    for (const auto& [shape, what] : {std::pair<const std::vector<int64_t>*, const char*>{&info.latent_shape, "latent_shape"},
                                      {&info.cond_shape, "cond_shape"}}) {
      unsigned __int128 bytes = 4;
      for (auto d : *shape) bytes = std::min<unsigned __int128>(bytes * static_cast<uint64_t>(d), UINT64_MAX);
      if (bytes > limit)
        fail_hint("the file is damaged or not written by this toolkit; rebuild it",
                  "pair cache '{}': attribute {} [{}] needs {} bytes per record, more than a file of {} bytes can hold",
                  path, what, fmt::join(*shape, ", "), static_cast<uint64_t>(std::min<unsigned __int128>(bytes, UINT64_MAX)),
                  file_bytes);
    }
  }
  const std::vector<int64_t> lat{n, info.latent_shape[0], info.latent_shape[1]};
  const std::vector<int64_t> cnd{n, info.cond_shape[0], info.cond_shape[1]};
  info.latent_dtype = check_dataset(h.latent_pos.get(), "latent_pos", {"float16", "float32"}, lat, path);
  const auto neg_dt = check_dataset(h.latent_neg.get(), "latent_neg", {info.latent_dtype}, lat, path);
  (void)neg_dt;
  info.cond_dtype = check_dataset(h.cond.get(), "cond", {"float16", "float32"}, cnd, path);
  check_dataset(h.cond_len.get(), "cond_len", {"int32"}, {n}, path);
  check_dataset(h.kind.get(), "kind", {"uint8"}, {n}, path);
  check_dataset(h.weight.get(), "weight", {"float32"}, {n}, path);
  {
    H5Id t(H5Dget_type(h.id.get()));
    if (H5Tget_class(t.get()) != H5T_STRING)
      fail("pair cache '{}': dataset 'id' has dtype {}, expected string", path, type_name(t.get()));
    const auto got = dataset_dims(h.id.get());
    if (got != std::vector<int64_t>{n})
      fail("pair cache '{}': dataset 'id' has shape [{}], expected [{}]", path, fmt::join(got, ", "), n);
  }
  h.half = info.latent_dtype == "float16";
  // Counts per kind.
  if (n > 0) {
    std::vector<uint8_t> kinds(static_cast<size_t>(n));
    read_rows(h.kind.get(), H5T_NATIVE_UINT8, 0, n, kinds.data(), path, "kind");
    for (int64_t i = 0; i < n; ++i) {
      if (kinds[i] > 1) fail("pair cache '{}': record {}: dataset 'kind' holds {}, expected 0 or 1", path, i, kinds[i]);
      info.counts[kinds[i]]++;
    }
  }
}

// Memory type for reading a float16/float32 dataset without conversion.
H5Id float_mem_type(const std::string& dtype) {
  if (dtype == "float16") return make_f16_type();
  return H5Id(H5Tcopy(H5T_NATIVE_FLOAT));
}
torch::ScalarType torch_type(const std::string& dtype) {
  return dtype == "float16" ? torch::kFloat16 : torch::kFloat32;
}

// Plain single-threaded loops for the per-record work of the reader (these tensors are small, and
// torch's parallel kernels only add thread wake-ups next to the training threads).
torch::Tensor half_to_float(const torch::Tensor& h) {
  auto out = torch::empty(h.sizes(), torch::kFloat32);
  const auto* src = h.data_ptr<at::Half>();
  float* dst = out.data_ptr<float>();
  for (int64_t k = 0, n = h.numel(); k < n; ++k) dst[k] = static_cast<float>(src[k]);
  return out;
}
// Index of the first row (of `rows` equal rows) holding a non-finite value, or -1.
int64_t first_nonfinite_row(const torch::Tensor& t, int64_t rows) {
  const float* p = t.data_ptr<float>();
  const int64_t n = t.numel(), per = rows > 0 ? n / rows : 0;
  for (int64_t k = 0; k < n; ++k)
    if (!std::isfinite(p[k])) return k / per;
  return -1;
}

// Reads rows [start, start+count) of a float dataset as a float32 tensor [count, ...].
torch::Tensor read_float_rows(hid_t dset, const std::string& dtype, int64_t start, int64_t count,
                              const std::string& path, const std::string& name) {
  auto dims = dataset_dims(dset);
  dims[0] = count;
  auto t = torch::empty(dims, torch::TensorOptions().dtype(torch_type(dtype)));
  H5Id mt = float_mem_type(dtype);
  read_rows(dset, mt.get(), start, count, t.data_ptr(), path, name);
  return dtype == "float16" ? half_to_float(t) : t;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Crash isolation. libhdf5 1.10 (Debian 12) trusts several on-disk structures: a corrupted global
// heap (where variable-length strings such as the 'format' attribute and the ids live) makes
// H5Aread/H5Dread read out of bounds and crash (H5HG_read). HDF5 1.14 reports such files cleanly, 1.10
// cannot be fixed from outside. So the first reads of a file -- attributes, dataset headers, every
// id, and `pairs validate`'s full scan -- run in a forked child process: if libhdf5 crashes there,
// the caller gets a simu::Error naming the file; if the child succeeds, the same reads in this
// process touch exactly the bytes that were just read safely. SIMU_HDF5_ISOLATE=0 turns it off
// (debugging).

namespace {

// Runs fn in a forked child. fn may report progress through the callback it gets. Returns when fn
// succeeded; rethrows its simu::Error (same message and hint); throws a simu::Error naming the file
// when the child died (signal, sanitizer abort).
void isolated(const std::string& path, const char* what,
              const std::function<void(const std::function<void(int64_t, int64_t)>&)>& fn,
              const std::function<void(int64_t, int64_t)>& progress = nullptr) {
  const char* env = std::getenv("SIMU_HDF5_ISOLATE");
  if (env && std::string(env) == "0") {
    fn(progress ? progress : [](int64_t, int64_t) {});
    return;
  }
  int fds[2];
  if (::pipe(fds) != 0) fail("pair cache '{}': pipe(): {}", path, std::strerror(errno));
  pid_t pid;
  {
    // No other thread may be inside HDF5 while the child is forked (its state is copied).
    std::lock_guard<std::recursive_mutex> lock(hdf5_mutex());
    std::fflush(nullptr);
    pid = ::fork();
    if (pid == 0) {
      // Child: the only thread. The HDF5 mutex was copied locked by a thread id this process does not
      // have: make it a fresh one.
      new (&hdf5_mutex()) std::recursive_mutex();
      ::close(fds[0]);
      auto send = [&](const std::string& msg) {
        size_t done = 0;
        while (done < msg.size()) {
          const ssize_t k = ::write(fds[1], msg.data() + done, msg.size() - done);
          if (k <= 0) {
            if (k < 0 && errno == EINTR) continue;
            break;
          }
          done += static_cast<size_t>(k);
        }
      };
      int code = 0;
      try {
        fn([&](int64_t done, int64_t total) { send(fmt::format("P {} {}\n", done, total)); });
      } catch (const Error& e) {
        send(std::string("E") + e.what() + '\0' + e.hint());
        code = 3;
      } catch (const std::exception& e) {
        send(std::string("E") + "pair cache '" + path + "': " + e.what() + '\0');
        code = 3;
      }
      ::close(fds[1]);
      ::_exit(code);
    }
  }
  ::close(fds[1]);
  if (pid < 0) {
    ::close(fds[0]);
    fail("pair cache '{}': fork(): {}", path, std::strerror(errno));
  }
  // Progress lines ("P done total\n"), then possibly one error ("E<message>\0<hint>").
  std::string buf, error;
  bool in_error = false, hung = false;
  char chunk[4096];
  // Watchdog: libhdf5 1.10 also loops forever on some corrupt heaps; a child silent for longer than
  // SIMU_HDF5_TIMEOUT_S (default 120 s; progress lines reset it) is killed.
  const char* tenv = std::getenv("SIMU_HDF5_TIMEOUT_S");
  const int timeout_ms = 1000 * std::max(1, tenv ? std::atoi(tenv) : 120);
  while (true) {
    pollfd pfd{fds[0], POLLIN, 0};
    const int ready = ::poll(&pfd, 1, timeout_ms);
    if (ready < 0 && errno == EINTR) continue;
    if (ready == 0) {
      hung = true;
      ::kill(pid, SIGKILL);
      break;
    }
    const ssize_t k = ::read(fds[0], chunk, sizeof chunk);
    if (k < 0 && errno == EINTR) continue;
    if (k <= 0) break;
    buf.append(chunk, static_cast<size_t>(k));
    while (!in_error && !buf.empty()) {
      if (buf[0] == 'E') {
        in_error = true;
        break;
      }
      const auto nl = buf.find('\n');
      if (nl == std::string::npos) break;
      long long done = 0, total = 0;
      if (std::sscanf(buf.c_str(), "P %lld %lld", &done, &total) == 2 && progress) progress(done, total);
      buf.erase(0, nl + 1);
    }
  }
  ::close(fds[0]);
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  if (WIFEXITED(status) && WEXITSTATUS(status) == 0) return;
  if (WIFEXITED(status) && WEXITSTATUS(status) == 3 && in_error) {
    const auto zero = buf.find('\0');
    throw Error(buf.substr(1, zero == std::string::npos ? std::string::npos : zero - 1),
                zero == std::string::npos ? "" : buf.substr(zero + 1));
  }
  if (hung)
    fail_hint("the file is damaged: restore a copy or rebuild it (SIMU_HDF5_TIMEOUT_S raises the limit for huge files)",
              "pair cache '{}' is corrupt: reading its {} made libhdf5 1.10 loop for more than {} s (stopped; it ran in "
              "a separate process)",
              path, what, timeout_ms / 1000);
  const std::string how = WIFSIGNALED(status) ? fmt::format("signal {} ({})", WTERMSIG(status), strsignal(WTERMSIG(status)))
                                              : fmt::format("exit status {}", WEXITSTATUS(status));
  fail_hint("the file is damaged: restore a copy or rebuild it (h5py on HDF5 >= 1.14 may say which object is corrupt)",
            "pair cache '{}' is corrupt: reading its {} crashed libhdf5 1.10 ({}, in a separate process)", path, what,
            how);
}

// The structure checks of open_cache plus every id, in a child process (see isolated()).
void preflight(const std::string& path) {
  isolated(path, "structure and ids", [&](const std::function<void(int64_t, int64_t)>&) {
    CacheHandles h;
    open_cache(h, path, /*writable=*/false);
    H5Lock lock;
    (void)read_strings(h.id.get(), 0, h.info.size, path, "id");
  });
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Writer.

struct PairCacheWriter::Impl {
  CacheHandles h;
  std::vector<int64_t> latent_shape, cond_shape;
  torch::ScalarType dtype = torch::kFloat32;
  std::set<std::string> ids;
  int64_t n = 0;
  bool finished = false;
  std::string created_by;
};

PairCacheWriter::PairCacheWriter(const std::string& path, std::vector<int64_t> latent_shape,
                                 std::vector<int64_t> cond_shape, torch::ScalarType dtype, bool resume)
    : path_(path), tmp_path_(path + ".tmp-" + std::to_string(::getpid())), impl_(std::make_unique<Impl>()) {
  auto& m = *impl_;
  const std::string dt = dtype_str(dtype);
  SIMU_CHECK(latent_shape.size() == 2 && latent_shape[0] > 0 && latent_shape[1] > 0,
             "pair cache '{}': latent_shape must be [T, C] with T, C > 0, got [{}]", path, fmt::join(latent_shape, ", "));
  SIMU_CHECK(cond_shape.size() == 2 && cond_shape[0] > 0 && cond_shape[1] > 0,
             "pair cache '{}': cond_shape must be [L, Cc] with L, Cc > 0, got [{}]", path, fmt::join(cond_shape, ", "));
  m.latent_shape = latent_shape;
  m.cond_shape = cond_shape;
  m.dtype = dtype;
  const stdfs::path p(path);
  if (p.has_parent_path()) stdfs::create_directories(p.parent_path());
  // Resume: copy the finished cache and reopen the copy for appending.
  fs::remove_stale_temps(path);  // a killed writer's path.tmp-<pid>
  if (resume && stdfs::exists(path)) {
    try {
      preflight(path);
    } catch (const Error& e) {
      throw Error(fmt::format("cannot resume pair cache '{}': {}", path, e.what()), e.hint());
    }
    stdfs::copy_file(path, tmp_path_, stdfs::copy_options::overwrite_existing);
    try {
      open_cache(m.h, tmp_path_, /*writable=*/true);
    } catch (const Error& e) {
      m.h.close();
      stdfs::remove(tmp_path_);
      fail("cannot resume pair cache '{}': {}", path, e.what());
    }
    const auto& info = m.h.info;
    if (info.latent_shape != latent_shape || info.cond_shape != cond_shape || info.latent_dtype != dt ||
        info.cond_dtype != dt) {
      m.h.close();
      stdfs::remove(tmp_path_);
      fail("cannot resume pair cache '{}': it holds latents [{}] {} and cond [{}] {}, the writer was asked for "
           "latents [{}] {} and cond [{}] {}",
           path, fmt::join(info.latent_shape, ", "), info.latent_dtype, fmt::join(info.cond_shape, ", "),
           info.cond_dtype, fmt::join(latent_shape, ", "), dt, fmt::join(cond_shape, ", "), dt);
    }
    H5Lock lock;
    m.n = info.size;
    for (auto& s : read_strings(m.h.id.get(), 0, m.n, tmp_path_, "id")) m.ids.insert(std::move(s));
    return;
  }
  // Fresh file: root attributes and empty extendible datasets.
  H5Lock lock;
  H5Id fapl(H5Pcreate(H5P_FILE_ACCESS));
  H5Pset_fclose_degree(fapl.get(), H5F_CLOSE_STRONG);
  m.h.file = H5Id(check_id(H5Fcreate(tmp_path_.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, fapl.get()), tmp_path_,
                           "create file"));
  try {
    const hid_t f = m.h.file.get();
    write_attr_str(f, "format", kFormat, tmp_path_);
    write_attr_int(f, "schema_version", kPairCacheSchemaVersion, tmp_path_);
    write_attr_ints(f, "latent_shape", latent_shape, tmp_path_);
    write_attr_str(f, "cond_mode", "tokens", tmp_path_);
    write_attr_ints(f, "cond_shape", cond_shape, tmp_path_);
    write_attr_str(f, "created_by", kDefaultCreatedBy, tmp_path_);
    H5Id ftype = dtype == torch::kFloat16 ? make_f16_type() : H5Id(H5Tcopy(H5T_IEEE_F32LE));
    H5Id stype = make_vlen_string_type();
    m.h.latent_pos = create_rows_dataset(f, "latent_pos", ftype.get(), latent_shape, 1, true, tmp_path_);
    m.h.latent_neg = create_rows_dataset(f, "latent_neg", ftype.get(), latent_shape, 1, true, tmp_path_);
    m.h.cond = create_rows_dataset(f, "cond", ftype.get(), cond_shape, 1, true, tmp_path_);
    m.h.cond_len = create_rows_dataset(f, "cond_len", H5T_STD_I32LE, {}, kScalarChunk, true, tmp_path_);
    m.h.kind = create_rows_dataset(f, "kind", H5T_STD_U8LE, {}, kScalarChunk, true, tmp_path_);
    m.h.weight = create_rows_dataset(f, "weight", H5T_IEEE_F32LE, {}, kScalarChunk, true, tmp_path_);
    m.h.id = create_rows_dataset(f, "id", stype.get(), {}, kScalarChunk, false, tmp_path_);
    m.h.info.latent_dtype = m.h.info.cond_dtype = dt;
    m.h.half = dtype == torch::kFloat16;
  } catch (...) {
    m.h.close();
    stdfs::remove(tmp_path_);
    throw;
  }
}

PairCacheWriter::~PairCacheWriter() {
  if (!impl_ || impl_->finished) return;
  // Not finished: drop the temporary file; path keeps its previous state.
  impl_->h.close();
  std::error_code ec;
  stdfs::remove(tmp_path_, ec);
}

bool PairCacheWriter::contains(const std::string& id) const { return impl_->ids.count(id) != 0; }

int64_t PairCacheWriter::size() const { return impl_->n; }

void PairCacheWriter::set_created_by(const std::string& text) { impl_->created_by = text; }

void PairCacheWriter::append(const PairRecord& r) {
  auto& m = *impl_;
  if (m.finished) fail("pair cache '{}': append after finish()", path_);
  // Check the record before touching the file.
  if (r.id.empty()) fail("pair cache '{}': record {} has an empty id", path_, m.n);
  if (m.ids.count(r.id)) fail("pair cache '{}': pair id '{}' is already in the cache", path_, r.id);
  const auto kind = static_cast<uint8_t>(r.kind);
  if (kind > 1) fail("pair cache '{}': pair '{}': kind {} is not 0 or 1", path_, r.id, kind);
  if (!std::isfinite(r.weight) || r.weight < 0)
    fail("pair cache '{}': pair '{}': weight {} must be finite and >= 0", path_, r.id, r.weight);
  expect_shape(r.latent_pos, m.latent_shape, path_, r.id, "latent_pos");
  expect_shape(r.latent_neg, m.latent_shape, path_, r.id, "latent_neg");
  if (!r.cond.defined() || r.cond.dim() != 2 || r.cond.size(0) < 1 || r.cond.size(0) > m.cond_shape[0] ||
      r.cond.size(1) != m.cond_shape[1])
    fail("pair cache '{}': pair '{}': cond has shape [{}], expected [l, {}] with 1 <= l <= {}", path_, r.id,
         r.cond.defined() ? fmt::format("{}", fmt::join(r.cond.sizes(), ", ")) : std::string("undefined"),
         m.cond_shape[1], m.cond_shape[0]);
  expect_shape(r.cond, r.cond.sizes().vec(), path_, r.id, "cond");
  // Convert to the storage dtype (contiguous CPU) and pad the condition.
  auto pos = r.latent_pos.detach().to(torch::kCPU, m.dtype).contiguous();
  auto neg = r.latent_neg.detach().to(torch::kCPU, m.dtype).contiguous();
  const int32_t cond_len = static_cast<int32_t>(r.cond.size(0));
  auto cond = torch::zeros(m.cond_shape, torch::TensorOptions().dtype(m.dtype));
  cond.narrow(0, 0, cond_len).copy_(r.cond.detach().to(torch::kCPU, m.dtype));
  if (m.dtype == torch::kFloat16 &&
      !(torch::isfinite(pos).all().item<bool>() && torch::isfinite(neg).all().item<bool>() &&
        torch::isfinite(cond).all().item<bool>()))
    fail("pair cache '{}': pair '{}': values overflow float16 (|x| > 65504)", path_, r.id);
  // Grow every dataset by one row and write it.
  H5Lock lock;
  const int64_t i = m.n;
  const std::string& f = tmp_path_;
  H5Id mt = float_mem_type(dtype_str(m.dtype));
  for (auto* d : {&m.h.latent_pos, &m.h.latent_neg, &m.h.cond, &m.h.cond_len, &m.h.kind, &m.h.weight, &m.h.id})
    extend_rows(d->get(), i + 1, f, "dataset");
  write_rows(m.h.latent_pos.get(), mt.get(), i, 1, pos.data_ptr(), f, "latent_pos");
  write_rows(m.h.latent_neg.get(), mt.get(), i, 1, neg.data_ptr(), f, "latent_neg");
  write_rows(m.h.cond.get(), mt.get(), i, 1, cond.data_ptr(), f, "cond");
  write_rows(m.h.cond_len.get(), H5T_NATIVE_INT32, i, 1, &cond_len, f, "cond_len");
  write_rows(m.h.kind.get(), H5T_NATIVE_UINT8, i, 1, &kind, f, "kind");
  const float w = r.weight;
  write_rows(m.h.weight.get(), H5T_NATIVE_FLOAT, i, 1, &w, f, "weight");
  H5Id st = make_vlen_string_type();
  const char* idp = r.id.c_str();
  write_rows(m.h.id.get(), st.get(), i, 1, &idp, f, "id");
  m.n = i + 1;
  m.ids.insert(r.id);
}

void PairCacheWriter::finish() {
  auto& m = *impl_;
  if (m.finished) return;
  {
    H5Lock lock;
    if (!m.created_by.empty()) write_attr_str(m.h.file.get(), "created_by", m.created_by, tmp_path_);
    check_ok(H5Fflush(m.h.file.get(), H5F_SCOPE_GLOBAL), tmp_path_, "flush");
    for (H5Id* d : {&m.h.latent_pos, &m.h.latent_neg, &m.h.cond, &m.h.cond_len, &m.h.kind, &m.h.weight, &m.h.id})
      d->reset();
    if (!m.h.file.reset()) fail("pair cache '{}': closing the file failed: {}", tmp_path_, h5_error());
  }
  fsync_path(tmp_path_);
  fs::atomic_rename(tmp_path_, path_);
  m.finished = true;
}

// ---------------------------------------------------------------------------------------------
// Reader.

struct PairCacheReader::Impl {
  CacheHandles h;
  ~Impl() { h.close(); }
};

PairCacheReader PairCacheReader::open(const std::string& path) {
  PairCacheReader r;
  r.impl_ = std::make_shared<Impl>();
  if (!stdfs::exists(path)) fail("pair cache '{}' does not exist", path);
  preflight(path);
  open_cache(r.impl_->h, path, /*writable=*/false);
  return r;
}

const CacheInfo& PairCacheReader::info() const { return impl_->h.info; }
int64_t PairCacheReader::size() const { return impl_->h.info.size; }
const std::string& PairCacheReader::path() const { return impl_->h.info.path; }

PairRecord PairCacheReader::read(int64_t i) const {
  const auto& h = impl_->h;
  const auto& path = h.info.path;
  if (i < 0 || i >= h.info.size) fail("pair cache '{}': record {} out of range (size {})", path, i, h.info.size);
  PairRecord r;
  r.index = i;
  H5Lock lock;
  r.latent_pos = read_float_rows(h.latent_pos.get(), h.info.latent_dtype, i, 1, path, "latent_pos")[0];
  r.latent_neg = read_float_rows(h.latent_neg.get(), h.info.latent_dtype, i, 1, path, "latent_neg")[0];
  auto cond = read_float_rows(h.cond.get(), h.info.cond_dtype, i, 1, path, "cond")[0];
  int32_t len = 0;
  read_rows(h.cond_len.get(), H5T_NATIVE_INT32, i, 1, &len, path, "cond_len");
  if (len < 1 || len > h.info.cond_shape[0])
    fail("pair cache '{}': record {}: dataset 'cond_len' holds {}, expected 1..{}", path, i, len, h.info.cond_shape[0]);
  r.cond = cond.narrow(0, 0, len);
  uint8_t kind = 0;
  read_rows(h.kind.get(), H5T_NATIVE_UINT8, i, 1, &kind, path, "kind");
  if (kind > 1) fail("pair cache '{}': record {}: dataset 'kind' holds {}, expected 0 or 1", path, i, kind);
  r.kind = static_cast<PairKind>(kind);
  read_rows(h.weight.get(), H5T_NATIVE_FLOAT, i, 1, &r.weight, path, "weight");
  r.id = read_strings(h.id.get(), i, 1, path, "id")[0];
  // Non-finite values would poison training: refuse them here, naming the record.
  const std::pair<const torch::Tensor*, const char*> checks[] = {
      {&r.latent_pos, "latent_pos"}, {&r.latent_neg, "latent_neg"}, {&r.cond, "cond"}};
  for (const auto& [t, name] : checks)
    if (first_nonfinite_row(t->contiguous(), 1) >= 0)
      fail("pair cache '{}': record {} (id '{}'): dataset '{}' holds NaN or Inf", path, i, r.id, name);
  if (!std::isfinite(r.weight) || r.weight < 0)
    fail("pair cache '{}': record {} (id '{}'): dataset 'weight' holds {}, expected finite >= 0", path, i, r.id,
         r.weight);
  return r;
}

std::vector<std::string> PairCacheReader::ids() const {
  H5Lock lock;
  return read_strings(impl_->h.id.get(), 0, size(), path(), "id");
}

torch::Tensor PairCacheReader::kinds() const {
  auto t = torch::empty({size()}, torch::kUInt8);
  H5Lock lock;
  if (size() > 0) read_rows(impl_->h.kind.get(), H5T_NATIVE_UINT8, 0, size(), t.data_ptr(), path(), "kind");
  return t;
}

torch::Tensor PairCacheReader::weights() const {
  auto t = torch::empty({size()}, torch::kFloat32);
  H5Lock lock;
  if (size() > 0) read_rows(impl_->h.weight.get(), H5T_NATIVE_FLOAT, 0, size(), t.data_ptr(), path(), "weight");
  return t;
}

// ---------------------------------------------------------------------------------------------
// Dataset description and full validation.

std::vector<DatasetInfo> describe_datasets(const std::string& path) {
  H5Lock lock;
  if (H5Fis_hdf5(path.c_str()) <= 0) fail("pair cache '{}' is not a readable HDF5 file", path);
  H5Id file(check_id(H5Fopen(path.c_str(), H5F_ACC_RDONLY, reader_fapl().get()), path, "open"));
  // Names of the root's members.
  std::vector<std::string> names;
  H5Literate(
      file.get(), H5_INDEX_NAME, H5_ITER_INC, nullptr,
      [](hid_t, const char* name, const H5L_info_t*, void* data) -> herr_t {
        static_cast<std::vector<std::string>*>(data)->emplace_back(name);
        return 0;
      },
      &names);
  std::vector<DatasetInfo> out;
  for (const auto& name : names) {
    H5O_info_t oi;
    if (H5Oget_info_by_name(file.get(), name.c_str(), &oi, H5P_DEFAULT) < 0 || oi.type != H5O_TYPE_DATASET) continue;
    H5Id d(check_id(H5Dopen2(file.get(), name.c_str(), H5P_DEFAULT), path, "open dataset " + name));
    DatasetInfo di;
    di.name = name;
    H5Id t(H5Dget_type(d.get()));
    di.dtype = type_name(t.get());
    di.shape = dataset_dims(d.get());
    H5Id dcpl(H5Dget_create_plist(d.get()));
    if (H5Pget_layout(dcpl.get()) == H5D_CHUNKED) {
      std::vector<hsize_t> c(di.shape.size());
      H5Pget_chunk(dcpl.get(), static_cast<int>(c.size()), c.data());
      di.chunk.assign(c.begin(), c.end());
    }
    const int nf = H5Pget_nfilters(dcpl.get());
    for (int k = 0; k < nf; ++k) {
      unsigned flags = 0, cd[8];
      size_t ncd = 8;
      char fname[64] = {0};
      const H5Z_filter_t fid = H5Pget_filter2(dcpl.get(), k, &flags, &ncd, cd, sizeof fname, fname, nullptr);
      if (fid == H5Z_FILTER_DEFLATE)
        di.filters.push_back(fmt::format("gzip({})", ncd > 0 ? cd[0] : 0));
      else if (fid == H5Z_FILTER_SHUFFLE)
        di.filters.push_back("shuffle");
      else
        di.filters.push_back(fname[0] ? std::string(fname) : fmt::format("filter-{}", fid));
    }
    out.push_back(std::move(di));
  }
  return out;
}

namespace {
CacheInfo validate_in_process(const std::string& path, const std::function<void(int64_t, int64_t)>& progress);
}  // namespace

CacheInfo validate_cache(const std::string& path, const std::function<void(int64_t, int64_t)>& progress) {
  if (!stdfs::exists(path)) fail("pair cache '{}' does not exist", path);
  // The full scan runs in a child process (a corrupt file cannot crash the caller, see isolated());
  // the info then comes from a structure read in this process.
  isolated(path, "records", [&](const std::function<void(int64_t, int64_t)>& report) {
    (void)validate_in_process(path, report);
  }, progress);
  CacheHandles h;
  open_cache(h, path, /*writable=*/false);
  return h.info;
}

namespace {
CacheInfo validate_in_process(const std::string& path, const std::function<void(int64_t, int64_t)>& progress) {
  // Structure: attributes, datasets, dtypes, shapes, kinds (open_cache checks them all).
  CacheHandles h;
  open_cache(h, path, /*writable=*/false);
  const auto& info = h.info;
  const int64_t n = info.size;
  const int64_t max_len = info.cond_shape[0];
  H5Lock lock;
  // Ids: non-empty and unique.
  const auto ids = read_strings(h.id.get(), 0, n, path, "id");
  std::map<std::string, int64_t> seen;
  for (int64_t i = 0; i < n; ++i) {
    if (ids[i].empty()) fail("pair cache '{}': record {}: dataset 'id' holds an empty id", path, i);
    auto [it, fresh] = seen.emplace(ids[i], i);
    if (!fresh) fail("pair cache '{}': record {}: id '{}' repeats record {}", path, i, ids[i], it->second);
  }
  // Per-pair scalars: weight finite and >= 0, cond_len in 1..L.
  if (n > 0) {
    std::vector<float> w(n);
    std::vector<int32_t> len(n);
    read_rows(h.weight.get(), H5T_NATIVE_FLOAT, 0, n, w.data(), path, "weight");
    read_rows(h.cond_len.get(), H5T_NATIVE_INT32, 0, n, len.data(), path, "cond_len");
    for (int64_t i = 0; i < n; ++i) {
      if (!std::isfinite(w[i]) || w[i] < 0)
        fail("pair cache '{}': record {} (id '{}'): dataset 'weight' holds {}, expected finite >= 0", path, i, ids[i], w[i]);
      if (len[i] < 1 || len[i] > max_len)
        fail("pair cache '{}': record {} (id '{}'): dataset 'cond_len' holds {}, expected 1..{}", path, i, ids[i], len[i],
             max_len);
    }
  }
  // Large datasets in blocks of records: every value decodes and is finite.
  constexpr int64_t kBlock = 32;
  if (progress) progress(0, n);
  for (int64_t start = 0; start < n; start += kBlock) {
    const int64_t count = std::min(kBlock, n - start);
    const std::pair<hid_t, const char*> sets[] = {
        {h.latent_pos.get(), "latent_pos"}, {h.latent_neg.get(), "latent_neg"}, {h.cond.get(), "cond"}};
    for (const auto& [dset, name] : sets) {
      const auto& dt = std::string(name) == "cond" ? info.cond_dtype : info.latent_dtype;
      auto t = read_float_rows(dset, dt, start, count, path, name);  // [count, ...]
      const int64_t row = first_nonfinite_row(t, count);
      if (row >= 0) {
        const int64_t bad = start + row;
        fail("pair cache '{}': record {} (id '{}'): dataset '{}' holds NaN or Inf", path, bad, ids[bad], name);
      }
    }
    if (progress) progress(start + count, n);
  }
  return info;
}
}  // namespace

// ---------------------------------------------------------------------------------------------
// Synthetic cache.

void make_synthetic_cache(const std::string& path, int64_t n, std::vector<int64_t> latent_shape,
                          std::vector<int64_t> cond_shape, uint64_t seed, torch::ScalarType dtype,
                          const std::function<void(int64_t, int64_t)>& progress, int64_t cond_len_min) {
  SIMU_CHECK(n >= 1, "synthetic pair cache '{}': n must be >= 1, got {}", path, n);
  SIMU_CHECK(cond_shape.size() == 2 && cond_len_min <= cond_shape[0],
             "synthetic pair cache '{}': the minimum condition length {} exceeds the maximum {}", path, cond_len_min,
             cond_shape.empty() ? 0 : cond_shape[0]);
  PairCacheWriter writer(path, latent_shape, cond_shape, dtype);
  writer.set_created_by(fmt::format("simuscene_resampler make_synthetic_cache(seed={})", seed));
  auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  std::mt19937_64 rng(splitmix64(seed));
  const int64_t T = latent_shape[0], C = latent_shape[1], L = cond_shape[0], Cc = cond_shape[1];
  const auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  if (progress) progress(0, n);
  for (int64_t i = 0; i < n; ++i) {
    PairRecord r;
    r.id = fmt::format("syn-{:06d}", i);
    // Kinds: about 2/3 occlusion-completion; records 0 and 1 fix one of each so both kinds occur.
    const bool clean = i < 2 ? i == 1 : (rng() % 3 == 0);
    r.kind = clean ? PairKind::CleanPreservation : PairKind::OcclusionCompletion;
    r.weight = default_weight(r.kind);
    // Preferred latent: a smooth random field along tokens (running mean of white noise), unit scale.
    auto white = torch::randn({T + 7, C}, gen, f32);
    auto pos = white.unfold(0, 8, 1).mean(-1) * std::sqrt(8.0f);  // [T, C]
    // Rejected latent: occlusion-completion -> large parts replaced by noise (the incomplete shape);
    // clean-preservation -> a mild perturbation of the preferred one.
    auto noise = torch::randn({T, C}, gen, f32);
    torch::Tensor neg;
    if (clean) {
      neg = pos + 0.25f * noise;
    } else {
      auto mask = (torch::rand({T, 1}, gen, f32) < 0.5f).to(torch::kFloat32);  // [T, 1]
      neg = pos * (1 - mask) + noise * mask;
    }
    r.latent_pos = pos;
    r.latent_neg = neg;
    // Condition tokens with a length in [lo, L] (lo = L/2 unless given).
    const int64_t lo = std::max<int64_t>(1, cond_len_min > 0 ? cond_len_min : L / 2);
    const int64_t len = lo + static_cast<int64_t>(rng() % static_cast<uint64_t>(L - lo + 1));
    r.cond = torch::randn({len, Cc}, gen, f32);
    writer.append(r);
    if (progress) progress(i + 1, n);
  }
  writer.finish();
}

// ---------------------------------------------------------------------------------------------
// Stream.

std::vector<int64_t> epoch_permutation(int64_t n, uint64_t seed, int64_t epoch) {
  std::vector<int64_t> perm(static_cast<size_t>(std::max<int64_t>(n, 0)));
  std::iota(perm.begin(), perm.end(), 0);
  std::mt19937_64 rng(splitmix64(seed ^ splitmix64(static_cast<uint64_t>(epoch) + 0x5851F42D4C957F2DULL)));
  // Fisher-Yates with an unbiased bounded draw by rejection (exactly specified, unlike
  // std::uniform_int_distribution, whose algorithm differs between standard libraries).
  for (int64_t i = n - 1; i > 0; --i) {
    const uint64_t range = static_cast<uint64_t>(i) + 1;
    const uint64_t limit = std::numeric_limits<uint64_t>::max() - std::numeric_limits<uint64_t>::max() % range;
    uint64_t x;
    do x = rng();
    while (x >= limit);
    std::swap(perm[i], perm[static_cast<int64_t>(x % range)]);
  }
  return perm;
}

PairStream::PairStream(std::string path, int rank, int world, int64_t global_batch, uint64_t seed, StreamPosition start,
                       int prefetch)
    : reader_(PairCacheReader::open(path)),
      rank_(rank),
      world_(world),
      global_batch_(global_batch),
      seed_(seed),
      prefetch_(static_cast<size_t>(std::max(prefetch, 1))) {
  SIMU_CHECK(world >= 1 && rank >= 0 && rank < world, "pair stream '{}': rank {} is not in 0..{}", path, rank, world - 1);
  SIMU_CHECK(global_batch >= 1 && global_batch % world == 0,
             "pair stream '{}': global batch {} must be a positive multiple of the world size {}", path, global_batch,
             world);
  const int64_t n = reader_.size();
  if (n < global_batch)
    fail_hint("use a larger cache or a smaller global batch",
              "pair stream '{}': the cache has {} pairs, fewer than one global batch of {}", path, n, global_batch);
  SIMU_CHECK(start.epoch >= 0 && start.step >= 0, "pair stream '{}': start position ({}, {}) is negative", path,
             start.epoch, start.step);
  local_batch_ = global_batch / world;
  steps_per_epoch_ = n / global_batch;
  // Normalize the start (a step past the epoch's end rolls over).
  start.epoch += start.step / steps_per_epoch_;
  start.step %= steps_per_epoch_;
  position_ = start;
  thread_ = std::thread([this, start] { produce(start); });
}

PairStream::~PairStream() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void PairStream::produce(StreamPosition pos) {
  std::vector<int64_t> perm;
  int64_t perm_epoch = -1;
  try {
    while (true) {
      // This rank's slice of the global batch at pos.
      if (perm_epoch != pos.epoch) {
        perm = epoch_permutation(reader_.size(), seed_, pos.epoch);
        perm_epoch = pos.epoch;
      }
      Item item;
      const int64_t base = pos.step * global_batch_ + rank_ * local_batch_;
      item.batch.reserve(static_cast<size_t>(local_batch_));
      for (int64_t k = 0; k < local_batch_; ++k) {
        {
          std::lock_guard<std::mutex> lock(mutex_);
          if (stop_) return;
        }
        item.batch.push_back(reader_.read(perm[base + k]));
      }
      // Advance, rolling over at the epoch's end.
      pos.step += 1;
      if (pos.step == steps_per_epoch_) {
        pos.step = 0;
        pos.epoch += 1;
      }
      item.after = pos;
      // Wait for room in the queue.
      std::unique_lock<std::mutex> lock(mutex_);
      cv_.wait(lock, [&] { return stop_ || queue_.size() < prefetch_; });
      if (stop_) return;
      queue_.push_back(std::move(item));
      cv_.notify_all();
    }
  } catch (...) {
    std::lock_guard<std::mutex> lock(mutex_);
    Item item;
    item.error = std::current_exception();
    queue_.push_back(std::move(item));
    cv_.notify_all();
  }
}

std::vector<PairRecord> PairStream::next_batch() {
  std::unique_lock<std::mutex> lock(mutex_);
  cv_.wait(lock, [&] { return !queue_.empty(); });
  auto& front = queue_.front();
  if (front.error) std::rethrow_exception(front.error);  // stays queued: every later call rethrows too
  Item item = std::move(front);
  queue_.pop_front();
  position_ = item.after;
  cv_.notify_all();
  return std::move(item.batch);
}

StreamPosition PairStream::position() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return position_;
}

// ---------------------------------------------------------------------------------------------
// Collate.

PairBatch collate(const std::vector<PairRecord>& records) {
  SIMU_CHECK(!records.empty(), "collate: no records");
  const auto& first = records.front();
  int64_t max_len = 0;
  for (const auto& r : records) {
    SIMU_CHECK(r.latent_pos.sizes() == first.latent_pos.sizes() && r.latent_neg.sizes() == first.latent_pos.sizes(),
               "collate: pair '{}' has latents [{}], expected [{}]", r.id, fmt::join(r.latent_pos.sizes(), ", "),
               fmt::join(first.latent_pos.sizes(), ", "));
    SIMU_CHECK(r.cond.dim() == 2 && r.cond.size(1) == first.cond.size(1),
               "collate: pair '{}' has cond [{}], expected [l, {}]", r.id, fmt::join(r.cond.sizes(), ", "),
               first.cond.size(1));
    max_len = std::max(max_len, r.cond.size(0));
  }
  const int64_t b = static_cast<int64_t>(records.size());
  PairBatch out;
  std::vector<torch::Tensor> pos, neg;
  out.cond = torch::zeros({b, max_len, first.cond.size(1)}, torch::kFloat32);  // [B, Lmax, Cc]
  out.cond_mask = torch::zeros({b, max_len}, torch::kBool);                    // [B, Lmax]
  out.weight = torch::empty({b}, torch::kFloat32);
  out.kind = torch::empty({b}, torch::kUInt8);
  for (int64_t i = 0; i < b; ++i) {
    const auto& r = records[i];
    pos.push_back(r.latent_pos.to(torch::kFloat32));
    neg.push_back(r.latent_neg.to(torch::kFloat32));
    const int64_t len = r.cond.size(0);
    out.cond[i].narrow(0, 0, len).copy_(r.cond);
    out.cond_mask[i].narrow(0, 0, len).fill_(true);
    out.weight[i] = r.weight;
    out.kind[i] = static_cast<int64_t>(r.kind);
    out.ids.push_back(r.id);
  }
  out.latent_pos = torch::stack(pos);  // [B, T, C]
  out.latent_neg = torch::stack(neg);  // [B, T, C]
  return out;
}

}  // namespace simu::data
