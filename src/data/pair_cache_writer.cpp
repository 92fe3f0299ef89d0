// Writing a pair cache: PairCacheWriter (atomic, resumable) and the synthetic cache maker
// (pair_cache.h).
#include <unistd.h>

#include <fmt/ranges.h>

#include <algorithm>
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

// "uint8" / "float16" / "float32".
std::string storage_mem_name(torch::ScalarType t) { return t == torch::kByte ? "uint8" : dtype_str(t); }

}  // namespace

struct PairCacheWriter::Impl {
  CacheHandles h;
  std::vector<int64_t> latent_shape, cond_shape;
  torch::ScalarType dtype = torch::kFloat32;
  bool inputs_mode = false;
  InputsLayout layout;  // inputs mode
  std::set<std::string> ids;
  int64_t n = 0;
  bool finished = false;
  std::string created_by;
};

PairCacheWriter::PairCacheWriter(const std::string& path, std::vector<int64_t> latent_shape,
                                 std::vector<int64_t> cond_shape, torch::ScalarType dtype, bool resume)
    : PairCacheWriter(path, std::move(latent_shape), std::move(cond_shape), dtype, nullptr, resume) {}

PairCacheWriter::PairCacheWriter(const std::string& path, std::vector<int64_t> latent_shape,
                                 std::vector<int64_t> cond_shape, torch::ScalarType dtype, const InputsLayout& layout,
                                 bool resume)
    : PairCacheWriter(path, std::move(latent_shape), std::move(cond_shape), dtype, &layout, resume) {}

PairCacheWriter::PairCacheWriter(const std::string& path, std::vector<int64_t> latent_shape,
                                 std::vector<int64_t> cond_shape, torch::ScalarType dtype, const InputsLayout* layout,
                                 bool resume)
    : path_(path), tmp_path_(path + ".tmp-" + std::to_string(::getpid())), impl_(std::make_unique<Impl>()) {
  auto& m = *impl_;
  (void)dtype_str(dtype);  // float16 / float32 only
  SIMU_CHECK(latent_shape.size() == 2 && latent_shape[0] > 0 && latent_shape[1] > 0,
             "pair cache '{}': latent_shape must be [T, C] with T, C > 0, got [{}]", path, fmt::join(latent_shape, ", "));
  SIMU_CHECK(cond_shape.size() == 2 && cond_shape[0] > 0 && cond_shape[1] > 0,
             "pair cache '{}': cond_shape must be [L, Cc] with L, Cc > 0, got [{}]", path, fmt::join(cond_shape, ", "));
  m.latent_shape = latent_shape;
  m.cond_shape = cond_shape;
  m.dtype = dtype;
  m.inputs_mode = layout != nullptr;
  if (layout) {
    m.layout = *layout;
    (void)InputsLayout::storage_named("exact", layout->image_size, layout->pointmap_size);  // sizes > 0
  }
  const stdfs::path p(path);
  if (p.has_parent_path()) stdfs::create_directories(p.parent_path());
  fs::remove_stale_temps(path);  // a killed writer's path.tmp-<pid>
  if (resume && stdfs::exists(path))
    resume_from(path);
  else
    create_fresh();
}

// Resume: copy the finished cache and reopen the copy for appending; it must hold what was asked for.
void PairCacheWriter::resume_from(const std::string& path) {
  auto& m = *impl_;
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
  const std::string dt = dtype_str(m.dtype);
  const auto describe = [](const std::vector<int64_t>& lat, const std::string& ldt, const std::string& mode,
                           const std::vector<int64_t>& cond, const std::string& cdt) {
    return fmt::format("latents [{}] {}, cond_mode {}, cond [{}] {}", fmt::join(lat, ", "), ldt, mode, fmt::join(cond, ", "), cdt);
  };
  const std::string want_mode = m.inputs_mode ? "inputs" : "tokens";
  const std::string want_cdt = m.inputs_mode ? fmt::format("inputs [{}, {}] {}/{}", m.layout.image_size, m.layout.pointmap_size,
                                                           storage_mem_name(m.layout.image_dtype), storage_mem_name(m.layout.pointmap_dtype))
                                             : dt;
  const std::string got_cdt = info.inputs_mode() ? fmt::format("inputs [{}] {}/{}", fmt::join(info.input_size, ", "),
                                                               info.image_dtype, info.pointmap_dtype)
                                                 : info.cond_dtype;
  if (info.latent_shape != m.latent_shape || info.cond_shape != m.cond_shape || info.latent_dtype != dt ||
      info.cond_mode != want_mode || got_cdt != want_cdt) {
    m.h.close();
    stdfs::remove(tmp_path_);
    fail("cannot resume pair cache '{}': it holds {}, the writer was asked for {}", path,
         describe(info.latent_shape, info.latent_dtype, info.cond_mode, info.cond_shape, got_cdt),
         describe(m.latent_shape, dt, want_mode, m.cond_shape, want_cdt));
  }
  H5Lock lock;
  m.n = info.size;
  for (auto& s : read_strings(m.h.id.get(), 0, m.n, tmp_path_, "id")) m.ids.insert(std::move(s));
}

// Fresh file: root attributes and empty extendible datasets.
void PairCacheWriter::create_fresh() {
  auto& m = *impl_;
  H5Lock lock;
  H5Id fapl(H5Pcreate(H5P_FILE_ACCESS));
  H5Pset_fclose_degree(fapl.get(), H5F_CLOSE_STRONG);
  m.h.file = H5Id(check_id(H5Fcreate(tmp_path_.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, fapl.get()), tmp_path_,
                           "create file"));
  try {
    const hid_t f = m.h.file.get();
    m.h.info.cond_mode = m.inputs_mode ? "inputs" : "tokens";
    write_attr_str(f, "format", kFormat, tmp_path_);
    write_attr_int(f, "schema_version", kPairCacheSchemaVersion, tmp_path_);
    write_attr_ints(f, "latent_shape", m.latent_shape, tmp_path_);
    write_attr_str(f, "cond_mode", m.h.info.cond_mode, tmp_path_);
    write_attr_ints(f, "cond_shape", m.cond_shape, tmp_path_);
    if (m.inputs_mode) write_attr_ints(f, "input_size", {m.layout.image_size, m.layout.pointmap_size}, tmp_path_);
    write_attr_str(f, "created_by", kDefaultCreatedBy, tmp_path_);
    H5Id ftype = m.dtype == torch::kFloat16 ? make_f16_type() : H5Id(H5Tcopy(H5T_IEEE_F32LE));
    H5Id stype = make_vlen_string_type();
    m.h.latent_pos = create_rows_dataset(f, "latent_pos", ftype.get(), m.latent_shape, 1, true, tmp_path_);
    m.h.latent_neg = create_rows_dataset(f, "latent_neg", ftype.get(), m.latent_shape, 1, true, tmp_path_);
    if (m.inputs_mode) {
      create_input_datasets(m.h, m.layout, tmp_path_);
    } else {
      m.h.cond = create_rows_dataset(f, "cond", ftype.get(), m.cond_shape, 1, true, tmp_path_);
      m.h.cond_len = create_rows_dataset(f, "cond_len", H5T_STD_I32LE, {}, kScalarChunk, true, tmp_path_);
      m.h.info.cond_dtype = dtype_str(m.dtype);
    }
    m.h.kind = create_rows_dataset(f, "kind", H5T_STD_U8LE, {}, kScalarChunk, true, tmp_path_);
    m.h.weight = create_rows_dataset(f, "weight", H5T_IEEE_F32LE, {}, kScalarChunk, true, tmp_path_);
    m.h.id = create_rows_dataset(f, "id", stype.get(), {}, kScalarChunk, false, tmp_path_);
    m.h.info.latent_dtype = dtype_str(m.dtype);
    m.h.half = m.dtype == torch::kFloat16;
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

namespace {

// The tokens-mode condition of a record: [L, Cc] in the storage dtype, zero padded, and its length.
torch::Tensor padded_tokens(const PairRecord& r, const std::vector<int64_t>& cond_shape, torch::ScalarType dtype,
                            const std::string& path, int32_t* len) {
  if (!r.inputs.empty())
    fail("pair cache '{}': pair '{}' gives condition inputs, but this cache stores condition tokens (cond_mode tokens)",
         path, r.id);
  if (!r.cond.defined() || r.cond.dim() != 2 || r.cond.size(0) < 1 || r.cond.size(0) > cond_shape[0] ||
      r.cond.size(1) != cond_shape[1])
    fail("pair cache '{}': pair '{}': cond has shape [{}], expected [l, {}] with 1 <= l <= {}", path, r.id,
         r.cond.defined() ? fmt::format("{}", fmt::join(r.cond.sizes(), ", ")) : std::string("undefined"),
         cond_shape[1], cond_shape[0]);
  expect_shape(r.cond, r.cond.sizes().vec(), path, r.id, "cond");
  *len = static_cast<int32_t>(r.cond.size(0));
  auto cond = torch::zeros(cond_shape, torch::TensorOptions().dtype(dtype));
  cond.narrow(0, 0, *len).copy_(r.cond.detach().to(torch::kCPU, dtype));
  if (dtype == torch::kFloat16 && !torch::isfinite(cond).all().item<bool>())
    fail("pair cache '{}': pair '{}': values overflow float16 (|x| > 65504)", path, r.id);
  return cond;
}

// The inputs-mode condition of a record: each input in its storage dtype (condition_input_names order).
std::vector<torch::Tensor> encoded_inputs(const PairRecord& r, const CacheInfo& info, const std::string& path) {
  if (r.cond.defined())
    fail("pair cache '{}': pair '{}' gives condition tokens, but this cache stores condition inputs (cond_mode inputs)",
         path, r.id);
  const auto& names = condition_input_names();
  for (const auto& [name, t] : r.inputs)
    if (std::find(names.begin(), names.end(), name) == names.end())
      fail("pair cache '{}': pair '{}': '{}' is not a condition input (expected {})", path, r.id, name, fmt::join(names, ", "));
  std::vector<torch::Tensor> out;
  for (size_t k = 0; k < names.size(); ++k) {
    const auto it = r.inputs.find(names[k]);
    out.push_back(encode_input(k, it == r.inputs.end() ? torch::Tensor() : it->second, info, path, r.id));
  }
  return out;
}

}  // namespace

void PairCacheWriter::append(const PairRecord& r) {
  auto& m = *impl_;
  if (m.finished) fail("pair cache '{}': append after finish()", path_);
  torch::Tensor pos, neg, cond;
  int32_t cond_len = 0;
  std::vector<torch::Tensor> inputs;
  try {
    // Check the record before touching the file; convert to the storage dtype (contiguous CPU); the
    // condition padded (tokens) or encoded (inputs).
    if (r.id.empty()) fail("pair cache '{}': record {} has an empty id", path_, m.n);
    if (m.ids.count(r.id)) fail("pair cache '{}': pair id '{}' is already in the cache", path_, r.id);
    if (static_cast<uint8_t>(r.kind) > 1)
      fail("pair cache '{}': pair '{}': kind {} is not 0 or 1", path_, r.id, static_cast<int>(r.kind));
    if (!std::isfinite(r.weight) || r.weight < 0)
      fail("pair cache '{}': pair '{}': weight {} must be finite and >= 0", path_, r.id, r.weight);
    expect_shape(r.latent_pos, m.latent_shape, path_, r.id, "latent_pos");
    expect_shape(r.latent_neg, m.latent_shape, path_, r.id, "latent_neg");
    pos = r.latent_pos.detach().to(torch::kCPU, m.dtype).contiguous();
    neg = r.latent_neg.detach().to(torch::kCPU, m.dtype).contiguous();
    if (m.dtype == torch::kFloat16 && !(torch::isfinite(pos).all().item<bool>() && torch::isfinite(neg).all().item<bool>()))
      fail("pair cache '{}': pair '{}': values overflow float16 (|x| > 65504)", path_, r.id);
    if (m.inputs_mode)
      inputs = encoded_inputs(r, m.h.info, path_);
    else
      cond = padded_tokens(r, m.cond_shape, m.dtype, path_, &cond_len);
  } catch (const RecordRefused&) {
    throw;
  } catch (const Error& e) {
    throw RecordRefused(e.what(), e.hint());
  }
  const auto kind = static_cast<uint8_t>(r.kind);
  // Grow every dataset by one row and write it.
  H5Lock lock;
  const int64_t i = m.n;
  const std::string& f = tmp_path_;
  H5Id mt = float_mem_type(dtype_str(m.dtype));
  for (auto* d : m.h.datasets()) extend_rows(d->get(), i + 1, f, "dataset");
  write_rows(m.h.latent_pos.get(), mt.get(), i, 1, pos.data_ptr(), f, "latent_pos");
  write_rows(m.h.latent_neg.get(), mt.get(), i, 1, neg.data_ptr(), f, "latent_neg");
  if (m.inputs_mode) {
    for (size_t k = 0; k < inputs.size(); ++k) {
      H5Id it = storage_mem_type(storage_mem_name(inputs[k].scalar_type()));
      write_rows(m.h.inputs[k].get(), it.get(), i, 1, inputs[k].data_ptr(), f, condition_input_names()[k]);
    }
  } else {
    write_rows(m.h.cond.get(), mt.get(), i, 1, cond.data_ptr(), f, "cond");
    write_rows(m.h.cond_len.get(), H5T_NATIVE_INT32, i, 1, &cond_len, f, "cond_len");
  }
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
    for (H5Id* d : m.h.datasets()) d->reset();
    if (!m.h.file.reset()) fail("pair cache '{}': closing the file failed: {}", tmp_path_, h5_error());
  }
  fsync_path(tmp_path_);
  fs::atomic_rename(tmp_path_, path_);
  m.finished = true;
}

// ---------------------------------------------------------------------------------------------
// Synthetic cache.

namespace {

// Synthetic pair i without its condition: id, kind (about 2/3 occlusion-completion; records 0 and 1
// fix one of each), default weight; preferred latent a smooth random field along tokens (running
// mean of white noise, unit scale); rejected latent: occlusion-completion -> large parts replaced by
// noise (the incomplete shape), clean-preservation -> a mild perturbation of the preferred one.
PairRecord synthetic_pair(int64_t i, at::Generator& gen, std::mt19937_64& rng, int64_t T, int64_t C) {
  const auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  PairRecord r;
  r.id = fmt::format("syn-{:06d}", i);
  const bool clean = i < 2 ? i == 1 : (rng() % 3 == 0);
  r.kind = clean ? PairKind::CleanPreservation : PairKind::OcclusionCompletion;
  r.weight = default_weight(r.kind);
  auto white = torch::randn({T + 7, C}, gen, f32);
  auto pos = white.unfold(0, 8, 1).mean(-1) * std::sqrt(8.0f);  // [T, C]
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
  return r;
}

// Synthetic condition inputs at the layout's sizes: smooth random images in [0, 1] (bilinear
// upsampling of an 8x8 grid), box masks (binary), a tilted plane as the point map.
std::map<std::string, torch::Tensor> synthetic_inputs(at::Generator& gen, const InputsLayout& l) {
  const auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  namespace F = torch::nn::functional;
  auto smooth = [&](int64_t ch, int64_t side) {
    auto g = torch::rand({1, ch, 8, 8}, gen, f32);
    return F::interpolate(g, F::InterpolateFuncOptions().size(std::vector<int64_t>{side, side}).mode(torch::kBilinear).align_corners(false))[0];
  };
  auto box = [&](int64_t side) {
    auto m = torch::zeros({1, side, side}, f32);
    const int64_t a = side / 4 + static_cast<int64_t>(torch::randint(0, std::max<int64_t>(1, side / 8), {1}, gen).item<int64_t>());
    m.slice(1, a, side - side / 4).slice(2, side / 4, side - a).fill_(1);
    return m;
  };
  auto plane = [&](int64_t side) {
    auto uv = torch::linspace(-1, 1, side, f32);
    auto z = 1 + 0.3f * torch::rand({1}, gen, f32) * uv.view({1, side});
    return torch::stack({-uv.view({1, side}).expand({side, side}), -uv.view({side, 1}).expand({side, side}),
                         z.expand({side, side})});  // [3, P, P]
  };
  return {{"image", smooth(3, l.image_size)},          {"rgb_image", smooth(3, l.image_size)},
          {"mask", box(l.image_size)},                 {"rgb_image_mask", box(l.image_size)},
          {"pointmap", plane(l.pointmap_size)},        {"rgb_pointmap", plane(l.pointmap_size)}};
}

}  // namespace

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
    PairRecord r = synthetic_pair(i, gen, rng, T, C);
    // Condition tokens with a length in [lo, L] (lo = L/2 unless given).
    const int64_t lo = std::max<int64_t>(1, cond_len_min > 0 ? cond_len_min : L / 2);
    const int64_t len = lo + static_cast<int64_t>(rng() % static_cast<uint64_t>(L - lo + 1));
    r.cond = torch::randn({len, Cc}, gen, f32);
    writer.append(r);
    if (progress) progress(i + 1, n);
  }
  writer.finish();
}

void make_synthetic_inputs_cache(const std::string& path, int64_t n, std::vector<int64_t> latent_shape,
                                 std::vector<int64_t> cond_shape, const InputsLayout& layout, uint64_t seed,
                                 torch::ScalarType dtype, const std::vector<std::map<std::string, torch::Tensor>>& examples,
                                 const std::function<void(int64_t, int64_t)>& progress) {
  SIMU_CHECK(n >= 1, "synthetic pair cache '{}': n must be >= 1, got {}", path, n);
  PairCacheWriter writer(path, latent_shape, cond_shape, dtype, layout);
  writer.set_created_by(fmt::format("simuscene_resampler make_synthetic_inputs_cache(seed={})", seed));
  auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  std::mt19937_64 rng(splitmix64(seed));
  if (progress) progress(0, n);
  for (int64_t i = 0; i < n; ++i) {
    PairRecord r = synthetic_pair(i, gen, rng, latent_shape.at(0), latent_shape.at(1));
    r.inputs = examples.empty() ? synthetic_inputs(gen, layout) : examples[static_cast<size_t>(i) % examples.size()];
    writer.append(r);
    if (progress) progress(i + 1, n);
  }
  writer.finish();
}

}  // namespace simu::data
