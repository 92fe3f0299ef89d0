// Reading a pair cache: PairCacheReader, the dataset description and the full validation scan
// (pair_cache.h).
#include <fmt/ranges.h>

#include <algorithm>
#include <filesystem>

#include "common/error.h"
#include "data/pair_cache_layout.h"

namespace simu::data {

namespace stdfs = std::filesystem;
using namespace h5;
using namespace layout;

struct PairCacheReader::Impl {
  CacheHandles h;
  PairColumns columns;  // ids, kinds, weights, cond_len: read whole at open
  ~Impl() { h.close(); }
};

PairCacheReader PairCacheReader::open(const std::string& path) {
  PairCacheReader r;
  r.impl_ = std::make_shared<Impl>();
  if (!stdfs::exists(path)) fail("pair cache '{}' does not exist", path);
  preflight(path);
  open_cache(r.impl_->h, path, /*writable=*/false);
  r.impl_->columns = read_pair_columns(r.impl_->h, path);
  return r;
}

const CacheInfo& PairCacheReader::info() const { return impl_->h.info; }
int64_t PairCacheReader::size() const { return impl_->h.info.size; }
const std::string& PairCacheReader::path() const { return impl_->h.info.path; }

PairRecord PairCacheReader::read(int64_t i) const {
  const auto& h = impl_->h;
  const auto& c = impl_->columns;  // the small per-pair datasets, read at open
  const auto& path = h.info.path;
  if (i < 0 || i >= h.info.size) fail("pair cache '{}': record {} out of range (size {})", path, i, h.info.size);
  PairRecord r;
  r.index = i;
  H5Lock lock;
  r.latent_pos = read_float_rows(h.latent_pos.get(), h.info.latent_dtype, i, 1, path, "latent_pos")[0];
  r.latent_neg = read_float_rows(h.latent_neg.get(), h.info.latent_dtype, i, 1, path, "latent_neg")[0];
  if (h.info.inputs_mode()) {
    const auto& names = condition_input_names();
    for (size_t k = 0; k < names.size(); ++k) r.inputs[names[k]] = read_input_rows(h, k, i, 1)[0];  // [ch, s, s]
  } else {
    auto cond = read_float_rows(h.cond.get(), h.info.cond_dtype, i, 1, path, "cond")[0];
    const int32_t len = c.cond_len[static_cast<size_t>(i)];
    if (len < 1 || len > h.info.cond_shape[0])
      fail("pair cache '{}': record {}: dataset 'cond_len' holds {}, expected 1..{}", path, i, len, h.info.cond_shape[0]);
    r.cond = cond.narrow(0, 0, len);
  }
  const uint8_t kind = c.kinds[static_cast<size_t>(i)];
  if (kind > 1) fail("pair cache '{}': record {}: dataset 'kind' holds {}, expected 0 or 1", path, i, kind);
  r.kind = static_cast<PairKind>(kind);
  r.weight = c.weights[static_cast<size_t>(i)];
  r.id = c.ids[static_cast<size_t>(i)];
  // Non-finite values would poison training: refuse them here, naming the record.
  const std::pair<const torch::Tensor*, const char*> checks[] = {
      {&r.latent_pos, "latent_pos"}, {&r.latent_neg, "latent_neg"}, {&r.cond, "cond"}};
  for (const auto& [t, name] : checks)
    if (t->defined() && first_nonfinite_row(t->contiguous(), 1) >= 0)
      fail("pair cache '{}': record {} (id '{}'): dataset '{}' holds NaN or Inf", path, i, r.id, name);
  for (const auto& [name, t] : r.inputs)
    if (const auto problem = check_condition_input(name, t); !problem.empty())
      fail("pair cache '{}': record {} (id '{}'): dataset '{}' {}", path, i, r.id, name, problem);
  if (!std::isfinite(r.weight) || r.weight < 0)
    fail("pair cache '{}': record {} (id '{}'): dataset 'weight' holds {}, expected finite >= 0", path, i, r.id,
         r.weight);
  return r;
}

std::vector<std::string> PairCacheReader::ids() const { return impl_->columns.ids; }

torch::Tensor PairCacheReader::kinds() const {
  const auto& k = impl_->columns.kinds;
  return torch::from_blob(const_cast<uint8_t*>(k.data()), {size()}, torch::kUInt8).clone();
}

torch::Tensor PairCacheReader::weights() const {
  const auto& w = impl_->columns.weights;
  return torch::from_blob(const_cast<float*>(w.data()), {size()}, torch::kFloat32).clone();
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

StorageBytes storage_bytes(const std::string& path) {
  CacheHandles h;
  open_cache(h, path, /*writable=*/false);
  StorageBytes b;
  b.pairs = h.info.size;
  std::error_code ec;
  b.file_bytes = static_cast<double>(stdfs::file_size(path, ec));
  H5Lock lock;
  auto bytes = [](const H5Id& d) { return d.valid() ? static_cast<double>(H5Dget_storage_size(d.get())) : 0.0; };
  b.latents = bytes(h.latent_pos) + bytes(h.latent_neg);
  b.condition = bytes(h.cond) + bytes(h.cond_len);
  for (const auto& d : h.inputs) b.condition += bytes(d);
  b.other = bytes(h.kind) + bytes(h.weight) + bytes(h.id);
  if (b.pairs > 0) {
    const double n = static_cast<double>(b.pairs);
    b.latents /= n, b.condition /= n, b.other /= n;
  }
  return b;
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

// Inputs mode: records [start, start+count) of every condition input decoded and checked.
void check_input_block(const CacheHandles& h, int64_t start, int64_t count, const std::vector<std::string>& ids) {
  const auto& names = condition_input_names();
  for (size_t k = 0; k < names.size(); ++k) {
    const auto block = read_input_rows(h, k, start, count);  // [count, ch, s, s]
    for (int64_t j = 0; j < count; ++j)
      if (const auto problem = check_condition_input(names[k], block[j]); !problem.empty())
        fail("pair cache '{}': record {} (id '{}'): dataset '{}' {}", h.info.path, start + j, ids[start + j], names[k],
             problem);
  }
}

CacheInfo validate_in_process(const std::string& path, const std::function<void(int64_t, int64_t)>& progress) {
  // Structure: attributes, datasets, dtypes, shapes, kinds (open_cache checks them all).
  CacheHandles h;
  open_cache(h, path, /*writable=*/false);
  const auto& info = h.info;
  const int64_t n = info.size;
  const int64_t max_len = info.cond_shape[0];
  const bool inputs = info.inputs_mode();
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
    std::vector<int32_t> len(n, 1);
    read_rows(h.weight.get(), H5T_NATIVE_FLOAT, 0, n, w.data(), path, "weight");
    if (!inputs) read_rows(h.cond_len.get(), H5T_NATIVE_INT32, 0, n, len.data(), path, "cond_len");
    for (int64_t i = 0; i < n; ++i) {
      if (!std::isfinite(w[i]) || w[i] < 0)
        fail("pair cache '{}': record {} (id '{}'): dataset 'weight' holds {}, expected finite >= 0", path, i, ids[i], w[i]);
      if (len[i] < 1 || len[i] > max_len)
        fail("pair cache '{}': record {} (id '{}'): dataset 'cond_len' holds {}, expected 1..{}", path, i, ids[i], len[i],
             max_len);
    }
  }
  // Large datasets in blocks of records: every value decodes and is finite (condition inputs:
  // check_condition_input per record).
  const int64_t kBlock = inputs ? 4 : 32;
  if (progress) progress(0, n);
  for (int64_t start = 0; start < n; start += kBlock) {
    const int64_t count = std::min(kBlock, n - start);
    std::vector<std::pair<hid_t, const char*>> sets = {{h.latent_pos.get(), "latent_pos"}, {h.latent_neg.get(), "latent_neg"}};
    if (!inputs) sets.push_back({h.cond.get(), "cond"});
    if (inputs) check_input_block(h, start, count, ids);
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

}  // namespace simu::data
