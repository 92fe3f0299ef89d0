// The Stage-1 sample cache (stage1_cache.h, docs/stage1_cache.md): writer, reader, bulk rows. The six
// condition-input datasets are the pair cache's inputs mode (pair_cache_inputs.cpp), reused through
// its layout helpers; errors those helpers raise are renamed from "pair cache" to "stage-1 cache".
#include "data/stage1_cache.h"

#include <unistd.h>

#include <fmt/ranges.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <set>
#include <tuple>

#include "common/error.h"
#include "common/fs.h"
#include "data/pair_cache_layout.h"

namespace simu::data {

namespace stdfs = std::filesystem;
using namespace h5;
using namespace layout;

namespace {

constexpr const char* kStage1Format = "simu.stage1_cache";
constexpr const char* kStage1CreatedBy = "simuscene_resampler Stage1CacheWriter";
// Records per chunk of the six inputs and the occupancy (docs/stage1_cache.md): a whole-cache load
// locates each chunk once, and libhdf5 1.10's lookup cost grows with the chunk's position
// (pair_cache_h5.h, locate_record_chunks), so fewer, larger chunks keep the load linear in practice.
constexpr hsize_t kRecordChunk = 16;

// Runs fn; a simu::Error from the pair cache's helpers is rethrown naming this cache.
template <class F>
auto renamed(F&& fn) -> decltype(fn()) {
  try {
    return fn();
  } catch (const RecordRefused&) {
    throw;
  } catch (const Error& e) {
    std::string msg = e.what();
    for (size_t at = msg.find("pair cache '"); at != std::string::npos; at = msg.find("pair cache '", at))
      msg.replace(at, 10, "stage-1 cache");
    throw Error(msg, e.hint());
  }
}

// The open datasets of a stage-1 cache: the inputs through the pair cache's handles (file, inputs,
// info.input_size / dtypes), the rest here.
struct Handles {
  CacheHandles h;  // file, inputs[6] and the inputs' CacheInfo fields
  H5Id occupancy, scale, shift, visible, split, family, id;
  std::vector<H5Id> pose;  // stage1_pose_latents() order
  std::vector<H5Id*> datasets() {
    std::vector<H5Id*> out{&occupancy, &scale, &shift, &visible, &split, &family, &id};
    for (auto& d : h.inputs) out.push_back(&d);
    for (auto& d : pose) out.push_back(&d);
    return out;
  }
  void close() {
    std::lock_guard<std::recursive_mutex> lock(hdf5_mutex());
    for (auto* d : datasets()) d->reset();
    h.close();
  }
  ~Handles() { close(); }
};

std::string pose_dataset(const std::string& latent) { return "pose_" + latent; }

// Opens every dataset of a file and checks attributes, dtypes and shapes; fills info.
void open_stage1(Handles& s, const std::string& path, Stage1CacheInfo& info) {
  H5Lock lock;
  if (!stdfs::exists(path)) fail("stage-1 cache '{}' does not exist", path);
  if (H5Fis_hdf5(path.c_str()) <= 0) {
    H5Eclear2(H5E_DEFAULT);
    fail_hint("the file may be truncated or corrupt; rebuild it (build_stage1_data)",
              "stage-1 cache '{}' is not a readable HDF5 file", path);
  }
  H5Id fapl = reader_fapl();
  const hid_t f = H5Fopen(path.c_str(), H5F_ACC_RDONLY, fapl.get());
  if (f < 0) fail("stage-1 cache '{}' cannot be opened: {}", path, h5_error());
  s.h.file = H5Id(f);
  const hid_t root = s.h.file.get();
  info.path = path;
  const auto format = read_attr_str(root, "format", path);
  if (format != kStage1Format)
    fail_hint("train_stage1 reads the caches build_stage1_data writes (a pair cache is another format)",
              "stage-1 cache '{}': attribute format is '{}', expected '{}'", path, format, kStage1Format);
  const auto version = read_attr_ints(root, "schema_version", path);
  if (version.size() != 1 || version[0] != kStage1CacheSchemaVersion)
    fail_hint("rebuild the cache with this toolkit (build_stage1_data)",
              "stage-1 cache '{}': schema_version [{}] is not supported (this build reads {})", path,
              fmt::join(version, ", "), kStage1CacheSchemaVersion);
  info.schema_version = static_cast<int>(version[0]);
  info.input_size = read_attr_ints(root, "input_size", path);
  const auto res = read_attr_ints(root, "occupancy_resolution", path);
  if (info.input_size.size() != 2 || info.input_size[0] <= 0 || info.input_size[1] <= 0 || res.size() != 1 ||
      res[0] < 2 || res[0] > 256)
    fail("stage-1 cache '{}': attributes input_size [{}] / occupancy_resolution [{}]: expected [S, P] > 0 and R in "
         "2..256", path, fmt::join(info.input_size, ", "), fmt::join(res, ", "));
  info.occupancy_resolution = res[0];
  info.pose_convention = read_attr_str(root, "pose_convention", path);
  info.created_by = read_attr_str(root, "created_by", path);
  s.id = open_dataset(root, "id", path);
  const auto id_dims = dataset_dims(s.id.get());
  if (id_dims.size() != 1) fail("stage-1 cache '{}': dataset 'id' must be one-dimensional", path);
  const int64_t n = id_dims[0];
  // At least one byte per record on disk (a corrupt header cannot make us allocate for more).
  std::error_code ec;
  const auto file_bytes = stdfs::file_size(path, ec);
  if (!ec && static_cast<uint64_t>(n) > file_bytes)
    fail("stage-1 cache '{}': dataset 'id' declares {} records, more than a file of {} bytes can hold", path, n, file_bytes);
  info.size = n;
  s.h.info.path = path;
  s.h.info.size = n;
  s.h.info.input_size = info.input_size;
  renamed([&] { open_input_datasets(s.h, path, n, /*multi_record=*/true); });
  info.image_dtype = s.h.info.image_dtype;
  info.pointmap_dtype = s.h.info.pointmap_dtype;
  const int64_t R = info.occupancy_resolution;
  renamed([&] {
    s.occupancy = open_dataset(root, "occupancy", path);
    check_dataset(s.occupancy.get(), "occupancy", {"uint8"}, {n, R, R, R}, path);
    check_record_layout(s.occupancy.get(), path, "occupancy", /*multi_record=*/true);
    for (const auto& [name, k] : stage1_pose_latents()) {
      s.pose.push_back(open_dataset(root, pose_dataset(name).c_str(), path));
      check_dataset(s.pose.back().get(), pose_dataset(name).c_str(), {"float32"}, {n, k}, path);
    }
    s.scale = open_dataset(root, "pointmap_scale", path);
    check_dataset(s.scale.get(), "pointmap_scale", {"float32"}, {n, 3}, path);
    s.shift = open_dataset(root, "pointmap_shift", path);
    check_dataset(s.shift.get(), "pointmap_shift", {"float32"}, {n, 3}, path);
    s.visible = open_dataset(root, "visible_fraction", path);
    check_dataset(s.visible.get(), "visible_fraction", {"float32"}, {n}, path);
    s.split = open_dataset(root, "split", path);
    check_dataset(s.split.get(), "split", {"uint8"}, {n}, path);
    s.family = open_dataset(root, "family", path);
    for (auto* d : {&s.family, &s.id}) {
      H5Id t(H5Dget_type(d->get()));
      if (H5Tget_class(t.get()) != H5T_STRING || H5Tis_variable_str(t.get()) <= 0 || dataset_dims(d->get()) != std::vector<int64_t>{n})
        fail("stage-1 cache '{}': datasets 'family' and 'id' must be [{}] variable-length strings", path, n);
    }
  });
}

// The small per-record datasets, read whole.
struct Columns {
  std::vector<std::string> ids, families;
  std::vector<uint8_t> splits;
  std::vector<float> visible;
};

Columns read_columns(const Handles& s, const Stage1CacheInfo& info) {
  const auto& path = info.path;
  const int64_t n = info.size;
  Columns c;
  H5Lock lock;
  c.ids = read_strings(s.id.get(), 0, n, path, "id");
  c.families = read_strings(s.family.get(), 0, n, path, "family");
  c.splits.resize(static_cast<size_t>(n));
  c.visible.resize(static_cast<size_t>(n));
  if (n > 0) {
    read_rows(s.split.get(), H5T_NATIVE_UINT8, 0, n, c.splits.data(), path, "split");
    read_rows(s.visible.get(), H5T_NATIVE_FLOAT, 0, n, c.visible.data(), path, "visible_fraction");
  }
  for (int64_t i = 0; i < n; ++i) {
    if (c.splits[i] > 2) fail("stage-1 cache '{}': record {}: dataset 'split' holds {}, expected 0, 1 or 2", path, i, c.splits[i]);
    if (!(c.visible[i] >= 0 && c.visible[i] <= 1))
      fail("stage-1 cache '{}': record {}: dataset 'visible_fraction' holds {}, expected [0, 1]", path, i, c.visible[i]);
  }
  return c;
}

// Why a pose latent / scale / shift value is not acceptable ("" when it is): [k] finite.
std::string check_vector(const torch::Tensor& t, int64_t k) {
  if (!t.defined()) return "is missing";
  if (t.numel() != k) return fmt::format("has {} values, expected {}", t.numel(), k);
  if (!torch::isfinite(t.to(torch::kFloat32)).all().item<bool>()) return "holds NaN or Inf";
  return "";
}

}  // namespace

const std::vector<std::pair<std::string, int64_t>>& stage1_pose_latents() {
  static const std::vector<std::pair<std::string, int64_t>> latents{
      {"6drotation_normalized", 6}, {"scale", 3}, {"translation", 3}, {"translation_scale", 1}};
  return latents;
}

const char* split_name(SampleSplit s) {
  switch (s) {
    case SampleSplit::Train: return "train";
    case SampleSplit::Val: return "val";
    case SampleSplit::Test: return "test";
  }
  return "?";
}

SampleSplit parse_sample_split(const std::string& name, const std::string& what) {
  for (auto s : {SampleSplit::Train, SampleSplit::Val, SampleSplit::Test})
    if (name == split_name(s)) return s;
  fail("{}: '{}' is not a split (expected train, val or test)", what, name);
}

// ---- writer -----------------------------------------------------------------------------------

struct Stage1CacheWriter::Impl {
  Handles s;
  int64_t R = 0;
  std::set<std::string> ids;
  int64_t n = 0;
  bool finished = false;
  std::string created_by;
};

Stage1CacheWriter::Stage1CacheWriter(const std::string& path, const InputsLayout& layout, int64_t occupancy_resolution,
                                     const std::string& pose_convention)
    : path_(path), tmp_path_(path + ".tmp-" + std::to_string(::getpid())), impl_(std::make_unique<Impl>()) {
  auto& m = *impl_;
  SIMU_CHECK(occupancy_resolution >= 2 && occupancy_resolution <= 256,
             "stage-1 cache '{}': occupancy resolution {} outside 2..256", path, occupancy_resolution);
  (void)InputsLayout::storage_named("exact", layout.image_size, layout.pointmap_size);  // sizes > 0
  m.R = occupancy_resolution;
  const stdfs::path p(path);
  if (p.has_parent_path()) stdfs::create_directories(p.parent_path());
  fs::remove_stale_temps(path);
  H5Lock lock;
  m.s.h.file = H5Id(check_id(H5Fcreate(tmp_path_.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT), tmp_path_, "create file"));
  try {
    const hid_t f = m.s.h.file.get();
    write_attr_str(f, "format", kStage1Format, tmp_path_);
    write_attr_int(f, "schema_version", kStage1CacheSchemaVersion, tmp_path_);
    write_attr_ints(f, "input_size", {layout.image_size, layout.pointmap_size}, tmp_path_);
    write_attr_int(f, "occupancy_resolution", m.R, tmp_path_);
    write_attr_str(f, "pose_convention", pose_convention, tmp_path_);
    write_attr_str(f, "created_by", kStage1CreatedBy, tmp_path_);
    m.s.h.info.path = tmp_path_;
    renamed([&] { create_input_datasets(m.s.h, layout, tmp_path_, kRecordChunk); });
    H5Id stype = make_vlen_string_type();
    m.s.occupancy = create_rows_dataset(f, "occupancy", H5T_STD_U8LE, {m.R, m.R, m.R}, kRecordChunk, true, tmp_path_,
                                        2 * kRecordChunk * static_cast<size_t>(m.R * m.R * m.R) + (1 << 16));
    for (const auto& [name, k] : stage1_pose_latents())
      m.s.pose.push_back(create_rows_dataset(f, pose_dataset(name), H5T_IEEE_F32LE, {k}, kScalarChunk, true, tmp_path_));
    m.s.scale = create_rows_dataset(f, "pointmap_scale", H5T_IEEE_F32LE, {3}, kScalarChunk, true, tmp_path_);
    m.s.shift = create_rows_dataset(f, "pointmap_shift", H5T_IEEE_F32LE, {3}, kScalarChunk, true, tmp_path_);
    m.s.visible = create_rows_dataset(f, "visible_fraction", H5T_IEEE_F32LE, {}, kScalarChunk, true, tmp_path_);
    m.s.split = create_rows_dataset(f, "split", H5T_STD_U8LE, {}, kScalarChunk, true, tmp_path_);
    m.s.family = create_rows_dataset(f, "family", stype.get(), {}, kScalarChunk, false, tmp_path_);
    m.s.id = create_rows_dataset(f, "id", stype.get(), {}, kScalarChunk, false, tmp_path_);
  } catch (...) {
    m.s.close();
    stdfs::remove(tmp_path_);
    throw;
  }
}

Stage1CacheWriter::~Stage1CacheWriter() {
  if (!impl_ || impl_->finished) return;
  impl_->s.close();
  std::error_code ec;
  stdfs::remove(tmp_path_, ec);
}

int64_t Stage1CacheWriter::size() const { return impl_->n; }

void Stage1CacheWriter::set_created_by(const std::string& text) { impl_->created_by = text; }

void Stage1CacheWriter::append(const Stage1Record& r) {
  auto& m = *impl_;
  if (m.finished) fail("stage-1 cache '{}': append after finish()", path_);
  // Check and encode everything before touching the file.
  std::vector<torch::Tensor> inputs, pose;
  torch::Tensor occ, scale, shift;
  try {
    if (r.id.empty()) fail("stage-1 cache '{}': record {} has an empty id", path_, m.n);
    if (m.ids.count(r.id)) fail("stage-1 cache '{}': sample id '{}' is already in the cache", path_, r.id);
    if (r.family.empty()) fail("stage-1 cache '{}': sample '{}': empty family", path_, r.id);
    if (!(r.visible_fraction >= 0 && r.visible_fraction <= 1))
      fail("stage-1 cache '{}': sample '{}': visible fraction {} outside [0, 1]", path_, r.id, r.visible_fraction);
    if (static_cast<uint8_t>(r.split) > 2) fail("stage-1 cache '{}': sample '{}': split {} unknown", path_, r.id, static_cast<int>(r.split));
    const auto& names = condition_input_names();
    for (const auto& [name, t] : r.inputs)
      if (std::find(names.begin(), names.end(), name) == names.end())
        fail("stage-1 cache '{}': sample '{}': '{}' is not a condition input (expected {})", path_, r.id, name,
             fmt::join(names, ", "));
    renamed([&] {
      for (size_t k = 0; k < names.size(); ++k) {
        const auto it = r.inputs.find(names[k]);
        inputs.push_back(encode_input(k, it == r.inputs.end() ? torch::Tensor() : it->second, m.s.h.info, path_, r.id));
      }
    });
    const std::vector<int64_t> cube{m.R, m.R, m.R};
    if (!r.occupancy.defined() || r.occupancy.sizes().vec() != cube)
      fail("stage-1 cache '{}': sample '{}': occupancy must be [{}, {}, {}]", path_, r.id, m.R, m.R, m.R);
    occ = r.occupancy.to(torch::kCPU).contiguous();
    if (occ.scalar_type() != torch::kByte) occ = occ.to(torch::kByte);
    if (occ.max().item<int>() > 1 || !torch::equal(occ.to(r.occupancy.scalar_type()), r.occupancy.to(torch::kCPU)))
      fail("stage-1 cache '{}': sample '{}': occupancy holds values other than 0 and 1", path_, r.id);
    for (const auto& [name, k] : stage1_pose_latents()) {
      const auto it = r.pose.find(name);
      const auto problem = check_vector(it == r.pose.end() ? torch::Tensor() : it->second, k);
      if (!problem.empty()) fail("stage-1 cache '{}': sample '{}': pose latent '{}' {}", path_, r.id, name, problem);
      pose.push_back(it->second.detach().to(torch::kCPU, torch::kFloat32).contiguous().view({k}));
    }
    for (auto [t, what, out] : {std::tuple{&r.pointmap_scale, "pointmap_scale", &scale}, std::tuple{&r.pointmap_shift, "pointmap_shift", &shift}}) {
      const auto problem = check_vector(*t, 3);
      if (!problem.empty()) fail("stage-1 cache '{}': sample '{}': {} {}", path_, r.id, what, problem);
      *out = t->detach().to(torch::kCPU, torch::kFloat32).contiguous();
    }
  } catch (const RecordRefused&) {
    throw;
  } catch (const Error& e) {
    throw RecordRefused(e.what(), e.hint());
  }
  H5Lock lock;
  const int64_t i = m.n;
  const std::string& f = tmp_path_;
  for (auto* d : m.s.datasets()) extend_rows(d->get(), i + 1, f, "dataset");
  const auto& names = condition_input_names();
  for (size_t k = 0; k < inputs.size(); ++k) {
    H5Id it = storage_mem_type(inputs[k].scalar_type() == torch::kByte ? "uint8" : dtype_str(inputs[k].scalar_type()));
    write_rows(m.s.h.inputs[k].get(), it.get(), i, 1, inputs[k].data_ptr(), f, names[k]);
  }
  write_rows(m.s.occupancy.get(), H5T_NATIVE_UINT8, i, 1, occ.data_ptr(), f, "occupancy");
  for (size_t k = 0; k < pose.size(); ++k)
    write_rows(m.s.pose[k].get(), H5T_NATIVE_FLOAT, i, 1, pose[k].data_ptr(), f, pose_dataset(stage1_pose_latents()[k].first));
  write_rows(m.s.scale.get(), H5T_NATIVE_FLOAT, i, 1, scale.data_ptr(), f, "pointmap_scale");
  write_rows(m.s.shift.get(), H5T_NATIVE_FLOAT, i, 1, shift.data_ptr(), f, "pointmap_shift");
  write_rows(m.s.visible.get(), H5T_NATIVE_FLOAT, i, 1, &r.visible_fraction, f, "visible_fraction");
  const auto split = static_cast<uint8_t>(r.split);
  write_rows(m.s.split.get(), H5T_NATIVE_UINT8, i, 1, &split, f, "split");
  H5Id st = make_vlen_string_type();
  const char* fam = r.family.c_str();
  write_rows(m.s.family.get(), st.get(), i, 1, &fam, f, "family");
  const char* idp = r.id.c_str();
  write_rows(m.s.id.get(), st.get(), i, 1, &idp, f, "id");
  m.n = i + 1;
  m.ids.insert(r.id);
}

void Stage1CacheWriter::finish() {
  auto& m = *impl_;
  if (m.finished) return;
  {
    H5Lock lock;
    if (!m.created_by.empty()) write_attr_str(m.s.h.file.get(), "created_by", m.created_by, tmp_path_);
    check_ok(H5Fflush(m.s.h.file.get(), H5F_SCOPE_GLOBAL), tmp_path_, "flush");
    for (auto* d : m.s.datasets()) d->reset();
    if (!m.s.h.file.reset()) fail("stage-1 cache '{}': closing the file failed: {}", tmp_path_, h5_error());
  }
  fsync_path(tmp_path_);
  fs::atomic_rename(tmp_path_, path_);
  m.finished = true;
}

// ---- reader -----------------------------------------------------------------------------------

struct Stage1CacheReader::Impl {
  Handles s;
  Stage1CacheInfo info;
  Columns columns;
};

Stage1CacheReader Stage1CacheReader::open(const std::string& path) {
  if (!stdfs::exists(path))
    fail_hint("build one with build_stage1_data (docs/stage1_cache.md)", "stage-1 cache '{}' does not exist", path);
  // First reads in a child process (a corrupt file crashes libhdf5 1.10 there, not here).
  renamed([&] {
    isolated(path, "structure and per-record datasets", [&](const std::function<void(int64_t, int64_t)>&) {
      Handles s;
      Stage1CacheInfo info;
      open_stage1(s, path, info);
      (void)read_columns(s, info);
    });
  });
  Stage1CacheReader r;
  r.impl_ = std::make_shared<Impl>();
  auto& m = *r.impl_;
  renamed([&] {
    open_stage1(m.s, path, m.info);
    m.columns = read_columns(m.s, m.info);
  });
  for (auto sp : m.columns.splits) m.info.counts[sp]++;
  return r;
}

const Stage1CacheInfo& Stage1CacheReader::info() const { return impl_->info; }
int64_t Stage1CacheReader::size() const { return impl_->info.size; }
const std::vector<std::string>& Stage1CacheReader::ids() const { return impl_->columns.ids; }
const std::vector<std::string>& Stage1CacheReader::families() const { return impl_->columns.families; }
const std::vector<uint8_t>& Stage1CacheReader::splits() const { return impl_->columns.splits; }
const std::vector<float>& Stage1CacheReader::visible_fractions() const { return impl_->columns.visible; }

Stage1Rows Stage1CacheReader::read_rows(int64_t start, int64_t count) const {
  const auto& m = *impl_;
  const auto& path = m.info.path;
  const int64_t R = m.info.occupancy_resolution;
  if (start < 0 || count < 0 || start + count > m.info.size)
    fail("stage-1 cache '{}': records [{}, {}) out of range (size {})", path, start, start + count, m.info.size);
  Stage1Rows out;
  for (int64_t i = start; i < start + count; ++i) out.index.push_back(i);
  const auto& names = condition_input_names();
  // Under the HDF5 lock: where each record's chunks are (and the small pose rows); then, without it,
  // their bytes read and inflated, so that several threads can load at once.
  struct Pending {
    h5::RecordChunks chunks;
    torch::Tensor out;
  };
  std::vector<Pending> pending;
  renamed([&] {
    H5Lock lock;
    // A big dataset into `out` (its storage dtype): located now, decoded below when stored as read.
    auto locate = [&](hid_t dset, const std::string& dt, const std::string& name, torch::Tensor out) {
      if (count == 0) return;
      H5Id mt = storage_mem_type(dt);
      H5Id ft(H5Dget_type(dset));
      if (H5Tequal(ft.get(), mt.get()) > 0)
        pending.push_back({locate_record_chunks(dset, start, count, path, name, /*multi_record=*/true), out});
      else  // converting (e.g. big-endian)
        read_record_rows(dset, mt.get(), start, count, out.data_ptr(), path, name, /*multi_record=*/true);
    };
    for (size_t k = 0; k < names.size(); ++k) {
      const bool point = is_pointmap_input(k), mask = is_mask_input(k);
      const std::string& dt = mask ? std::string("uint8") : point ? m.info.pointmap_dtype : m.info.image_dtype;
      const int64_t side = input_side(k, m.s.h.info);
      const auto st = dt == "uint8" ? torch::kByte : dt == "float16" ? torch::kFloat16 : torch::kFloat32;
      out.inputs[names[k]] = torch::empty({count, input_channels(k), side, side}, st);
      locate(m.s.h.inputs[k].get(), dt, names[k], out.inputs[names[k]]);
    }
    out.occupancy = torch::empty({count, R, R, R}, torch::kByte);
    locate(m.s.occupancy.get(), "uint8", "occupancy", out.occupancy);
    for (size_t k = 0; k < stage1_pose_latents().size(); ++k) {
      const auto& [name, width] = stage1_pose_latents()[k];
      auto t = torch::empty({count, width}, torch::kFloat32);
      if (count > 0) h5::read_rows(m.s.pose[k].get(), H5T_NATIVE_FLOAT, start, count, t.data_ptr(), path, pose_dataset(name));
      out.pose[name] = t;
    }
  });
  renamed([&] {
    for (auto& p : pending) decode_record_chunks(p.chunks, p.out.data_ptr());
  });
  // Bulk checks, naming the first bad record.
  auto first_bad = [&](const torch::Tensor& bad_rows, const std::string& dataset, const std::string& what) {
    if (!bad_rows.any().item<bool>()) return;
    const int64_t i = start + bad_rows.nonzero()[0][0].item<int64_t>();
    fail("stage-1 cache '{}': record {} (id '{}'): dataset '{}' {}", path, i, m.columns.ids[i], dataset, what);
  };
  if (count == 0) return out;
  first_bad(out.occupancy.flatten(1).gt(1).any(1), "occupancy", "holds values other than 0 and 1");
  for (const auto& [name, t] : out.pose) first_bad(torch::isfinite(t).logical_not().any(1), pose_dataset(name), "holds NaN or Inf");
  for (size_t k = 0; k < names.size(); ++k) {
    const auto& t = out.inputs.at(names[k]);
    if (t.scalar_type() == torch::kByte) continue;  // levels k/255: always in [0, 1]
    const auto v = t.to(torch::kFloat32).flatten(1);
    if (is_pointmap_input(k)) first_bad(torch::isinf(v).any(1), names[k], "holds +-Inf (invalid points must be NaN)");
    else first_bad((v.lt(-0.25) | v.gt(1.25) | torch::isnan(v)).any(1), names[k], "holds values outside [-0.25, 1.25] or NaN");
  }
  return out;
}

Stage1Record Stage1CacheReader::read(int64_t i) const {
  const auto& m = *impl_;
  const auto& path = m.info.path;
  if (i < 0 || i >= m.info.size) fail("stage-1 cache '{}': record {} out of range (size {})", path, i, m.info.size);
  Stage1Record r;
  r.index = i;
  r.id = m.columns.ids[i];
  r.family = m.columns.families[i];
  r.split = static_cast<SampleSplit>(m.columns.splits[i]);
  r.visible_fraction = m.columns.visible[i];
  const auto rows = read_rows(i, 1);
  const auto& names = condition_input_names();
  renamed([&] {
    H5Lock lock;
    for (size_t k = 0; k < names.size(); ++k) r.inputs[names[k]] = read_input_rows(m.s.h, k, i, 1)[0];  // float32 [ch, s, s]
    r.pointmap_scale = torch::empty({3}, torch::kFloat32);
    r.pointmap_shift = torch::empty({3}, torch::kFloat32);
    h5::read_rows(m.s.scale.get(), H5T_NATIVE_FLOAT, i, 1, r.pointmap_scale.data_ptr(), path, "pointmap_scale");
    h5::read_rows(m.s.shift.get(), H5T_NATIVE_FLOAT, i, 1, r.pointmap_shift.data_ptr(), path, "pointmap_shift");
  });
  r.occupancy = rows.occupancy[0];
  for (const auto& [name, t] : rows.pose) r.pose[name] = t[0];
  return r;
}

}  // namespace simu::data
