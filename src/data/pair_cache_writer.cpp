// Writing a pair cache: PairCacheWriter (atomic, resumable) and the synthetic cache maker
// (pair_cache.h).
#include <unistd.h>

#include <fmt/ranges.h>

#include <cmath>
#include <filesystem>
#include <random>

#include "common/error.h"
#include "common/fs.h"
#include "common/random.h"
#include "data/pair_cache_layout.h"

namespace simu::data {

namespace stdfs = std::filesystem;
using namespace h5;
using namespace layout;

namespace {

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

}  // namespace simu::data
