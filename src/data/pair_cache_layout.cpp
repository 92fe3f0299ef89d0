// The pair cache's layout: structure checks of a file, float record decoding, kinds and weights
// (pair_cache_layout.h, pair_cache.h).
#include "data/pair_cache_layout.h"

#include <fmt/ranges.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <numeric>

#include "common/error.h"

namespace simu::data {

std::string kind_name(PairKind kind) {
  return kind == PairKind::OcclusionCompletion ? "occlusion_completion" : "clean_preservation";
}

float default_weight(PairKind kind) { return kind == PairKind::OcclusionCompletion ? 1.0f : 0.1f; }

namespace layout {

namespace stdfs = std::filesystem;
using namespace h5;

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
  check_storage(dset, name, t.get(), shape, path);
  return dt;
}

// A compact or contiguous dataset's stored bytes must hold its shape x dtype, checked before any row
// is read: libhdf5 1.10 copies a row selection out of a compact dataset's buffer without checking it
// against the buffer's size. (Chunked per-record datasets are read through read_record_rows, which
// checks each chunk.) A contiguous dataset with no storage yet (never written) reads as fill values.
void check_storage(hid_t dset, const char* name, hid_t type, const std::vector<int64_t>& shape,
                   const std::string& path) {
  H5Id dcpl(H5Dget_create_plist(dset));
  const H5D_layout_t layout = H5Pget_layout(dcpl.get());
  if (layout != H5D_COMPACT && layout != H5D_CONTIGUOUS) return;
  // Needed bytes, saturating (the shape was checked against the record count, itself bounded by the file).
  const double needed = std::accumulate(shape.begin(), shape.end(), static_cast<double>(H5Tget_size(type)),
                                        [](double a, int64_t d) { return a * static_cast<double>(d); });
  const double stored = static_cast<double>(H5Dget_storage_size(dset));
  if (layout == H5D_CONTIGUOUS && stored == 0) return;
  if (stored < needed)
    fail_hint("the file is truncated or corrupted; rewrite it (build_pairs, pairs make)",
              "pair cache '{}': dataset '{}' stores {:.0f} bytes ({} layout), its shape [{}] and dtype need {:.0f}",
              path, name, stored, layout == H5D_COMPACT ? "compact" : "contiguous", fmt::join(shape, ", "), needed);
}

namespace {

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

// Root attributes: format, schema version, latent and condition shapes, cond_mode, created_by.
void read_root_attributes(hid_t root, const std::string& path, CacheInfo& info) {
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
  if (info.cond_mode != "tokens" && info.cond_mode != "inputs")
    fail("pair cache '{}': attribute cond_mode is '{}', expected 'tokens' or 'inputs'", path, info.cond_mode);
  if (info.cond_shape.size() != 2 || info.cond_shape[0] <= 0 || info.cond_shape[1] <= 0)
    fail("pair cache '{}': attribute cond_shape is [{}], expected [L, Cc] with L, Cc > 0", path,
         fmt::join(info.cond_shape, ", "));
  if (!info.inputs_mode()) return;
  info.input_size = read_attr_ints(root, "input_size", path);
  if (info.input_size.size() != 2 || info.input_size[0] <= 0 || info.input_size[1] <= 0)
    fail("pair cache '{}': attribute input_size is [{}], expected [S, P] with S, P > 0 (cond_mode inputs)", path,
         fmt::join(info.input_size, ", "));
}

// Sizes from the file's header are checked against the file's length before anything is allocated
// for them: every pair stores at least its id (one byte or more), and one record's latents or
// condition cannot decode to more than kMaxExpansion times the file.
void check_sizes_fit_file(const std::string& path, const CacheInfo& info, int64_t n) {
  std::error_code ec;
  const uint64_t file_bytes = stdfs::file_size(path, ec);
  if (!ec && static_cast<uint64_t>(n) > file_bytes)
    fail_hint("the file is damaged or not written by this toolkit; rebuild it",
              "pair cache '{}': dataset 'latent_pos' declares {} records, more than a file of {} bytes can hold",
              path, n, file_bytes);
  const uint64_t limit = std::max<uint64_t>(uint64_t{1} << 20, kMaxExpansion * (ec ? 0 : file_bytes));
  // Inputs mode: a record's largest inputs are [3, S, S] and [3, P, P] (the tokens are not stored).
  const std::vector<int64_t> image_rec = info.inputs_mode() ? std::vector<int64_t>{3, info.input_size[0], info.input_size[0]}
                                                             : info.cond_shape;
  const std::vector<int64_t> point_rec = info.inputs_mode() ? std::vector<int64_t>{3, info.input_size[1], info.input_size[1]}
                                                             : info.cond_shape;
  for (const auto& [shape, what] : {std::pair<const std::vector<int64_t>*, const char*>{&info.latent_shape, "latent_shape"},
                                    {&image_rec, info.inputs_mode() ? "input_size" : "cond_shape"},
                                    {&point_rec, info.inputs_mode() ? "input_size" : "cond_shape"}}) {
    unsigned __int128 bytes = 4;
    for (auto d : *shape) bytes = std::min<unsigned __int128>(bytes * static_cast<uint64_t>(d), UINT64_MAX);
    if (bytes > limit)
      fail_hint("the file is damaged or not written by this toolkit; rebuild it",
                "pair cache '{}': attribute {} [{}] needs {} bytes per record, more than a file of {} bytes can hold",
                path, what, fmt::join(*shape, ", "), static_cast<uint64_t>(std::min<unsigned __int128>(bytes, UINT64_MAX)),
                file_bytes);
  }
}

// Datasets: dtypes and shapes against the attributes (N records); the kind counts.
void check_datasets(CacheHandles& h, const std::string& path, int64_t n) {
  auto& info = h.info;
  const std::vector<int64_t> lat{n, info.latent_shape[0], info.latent_shape[1]};
  const std::vector<int64_t> cnd{n, info.cond_shape[0], info.cond_shape[1]};
  info.latent_dtype = check_dataset(h.latent_pos.get(), "latent_pos", {"float16", "float32"}, lat, path);
  const auto neg_dt = check_dataset(h.latent_neg.get(), "latent_neg", {info.latent_dtype}, lat, path);
  check_record_layout(h.latent_pos.get(), path, "latent_pos");
  check_record_layout(h.latent_neg.get(), path, "latent_neg");
  (void)neg_dt;
  if (!info.inputs_mode()) {
    info.cond_dtype = check_dataset(h.cond.get(), "cond", {"float16", "float32"}, cnd, path);
    check_record_layout(h.cond.get(), path, "cond");
    check_dataset(h.cond_len.get(), "cond_len", {"int32"}, {n}, path);
  }
  check_dataset(h.kind.get(), "kind", {"uint8"}, {n}, path);
  check_dataset(h.weight.get(), "weight", {"float32"}, {n}, path);
  {
    H5Id t(H5Dget_type(h.id.get()));
    if (H5Tget_class(t.get()) != H5T_STRING)
      fail("pair cache '{}': dataset 'id' has dtype {}, expected string", path, type_name(t.get()));
    const auto got = dataset_dims(h.id.get());
    if (got != std::vector<int64_t>{n})
      fail("pair cache '{}': dataset 'id' has shape [{}], expected [{}]", path, fmt::join(got, ", "), n);
    // Fixed-length ids: stored bytes as for the others (variable-length ids are first read by the guard).
    if (H5Tis_variable_str(t.get()) <= 0) check_storage(h.id.get(), "id", t.get(), got, path);
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

}  // namespace

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
  const hid_t root = h.file.get();
  read_root_attributes(root, path, info);
  // Datasets: presence first (so a missing one is named), then dtypes and shapes.
  h.latent_pos = open_dataset(root, "latent_pos", path);
  h.latent_neg = open_dataset(root, "latent_neg", path);
  if (!info.inputs_mode()) {
    h.cond = open_dataset(root, "cond", path);
    h.cond_len = open_dataset(root, "cond_len", path);
  }
  h.kind = open_dataset(root, "kind", path);
  h.weight = open_dataset(root, "weight", path);
  h.id = open_dataset(root, "id", path);
  const auto pos_dims = dataset_dims(h.latent_pos.get());
  if (pos_dims.size() != 3)
    fail("pair cache '{}': dataset 'latent_pos' has shape [{}], expected [N, {}, {}]", path, fmt::join(pos_dims, ", "),
         info.latent_shape[0], info.latent_shape[1]);
  const int64_t n = pos_dims[0];
  info.size = n;
  check_sizes_fit_file(path, info, n);
  if (info.inputs_mode()) open_input_datasets(h, path, n);
  check_datasets(h, path, n);
}

// Memory type for reading a float16/float32 dataset without conversion.
H5Id float_mem_type(const std::string& dtype) {
  if (dtype == "float16") return make_f16_type();
  return H5Id(H5Tcopy(H5T_NATIVE_FLOAT));
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
                              const std::string& path, const std::string& name, bool multi_record) {
  auto dims = dataset_dims(dset);
  dims[0] = count;
  auto t = torch::empty(dims, torch::TensorOptions().dtype(torch_type(dtype)));
  H5Id mt = float_mem_type(dtype);
  read_record_rows(dset, mt.get(), start, count, t.data_ptr(), path, name, multi_record);
  return dtype == "float16" ? half_to_float(t) : t;
}

PairColumns read_pair_columns(const CacheHandles& h, const std::string& path) {
  const int64_t n = h.info.size;
  PairColumns c;
  H5Lock lock;
  c.ids = read_strings(h.id.get(), 0, n, path, "id");
  c.kinds.resize(static_cast<size_t>(n));
  c.weights.resize(static_cast<size_t>(n));
  if (n > 0) {
    read_rows(h.kind.get(), H5T_NATIVE_UINT8, 0, n, c.kinds.data(), path, "kind");
    read_rows(h.weight.get(), H5T_NATIVE_FLOAT, 0, n, c.weights.data(), path, "weight");
  }
  if (!h.info.inputs_mode()) {
    c.cond_len.resize(static_cast<size_t>(n));
    if (n > 0) read_rows(h.cond_len.get(), H5T_NATIVE_INT32, 0, n, c.cond_len.data(), path, "cond_len");
  }
  return c;
}

void preflight(const std::string& path) {
  isolated(path, "structure and per-pair datasets", [&](const std::function<void(int64_t, int64_t)>&) {
    CacheHandles h;
    open_cache(h, path, /*writable=*/false);
    (void)read_pair_columns(h, path);
  });
}

}  // namespace layout
}  // namespace simu::data
