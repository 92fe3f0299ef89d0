#include "pipeline/resample/pair_builder.h"

#include <ATen/CPUGeneratorImpl.h>
#include <fmt/format.h>
#include <fmt/ranges.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <set>

#include "common/error.h"
#include "common/random.h"
#include "common/fs.h"
#include "common/log.h"
#include "data/depth_io.h"
#include "models/ss_encoder.h"
#include "data/safetensors.h"

namespace simu::resample {

namespace {

// An existing file or an error naming the manifest key.
const std::string& existing(const std::string& path, const char* key) {
  SIMU_CHECK(std::filesystem::is_regular_file(path), "{}: file not found: {}", key, path);
  return path;
}

// A mask file [H, W] of the image's size with at least one object pixel.
torch::Tensor read_checked_mask(const std::string& path, const char* key, const std::string& image_path, int64_t H,
                                int64_t W) {
  auto m = data::read_mask(existing(path, key));
  SIMU_CHECK(m.size(0) == H && m.size(1) == W, "{} {} is {}x{} (H x W) but the image {} is {}x{}", key, path, m.size(0),
             m.size(1), image_path, H, W);
  SIMU_CHECK((m > 0).any().item<bool>(), "{} {} is empty (no pixel > 0)", key, path);
  return m;
}

// The preprocessed embedder inputs of every side of one record.
struct PreparedPair {
  PairManifestRecord record;
  std::map<std::string, torch::Tensor> pos, neg, cond;  // cond empty: the condition is `pos` (clean pairs)
};

// Reads a record's files and runs the official preprocessing on each side. Throws simu::Error naming
// the manifest key and file on any problem.
PreparedPair prepare_pair(const PairManifestRecord& r, const data::PreprocessConfig& pre) {
  PreparedPair p;
  p.record = r;
  // The (occluded or clean) image, its mask and point map.
  const auto rgb = data::read_image_rgb(existing(r.image, "image"));  // [3, H, W]
  const int64_t H = rgb.size(1), W = rgb.size(2);
  const auto mask = read_checked_mask(r.mask, "mask", r.image, H, W);
  const auto pointmap = r.pointmap.empty() ? default_pointmap(H, W) : load_pointmap_file(existing(r.pointmap, "pointmap"));
  if (r.kind == data::PairKind::OcclusionCompletion) {
    // Edited full-object image and full-object mask M' (same size as the occluded image).
    const auto full_rgb = data::read_image_rgb(existing(r.full_image, "full_image"));
    SIMU_CHECK(full_rgb.size(1) == H && full_rgb.size(2) == W, "full_image {} is {}x{} but the image {} is {}x{}",
               r.full_image, full_rgb.size(1), full_rgb.size(2), r.image, H, W);
    const auto full_mask = read_checked_mask(r.full_mask, "full_mask", r.full_image, H, W);
    const auto full_pointmap = !r.full_pointmap.empty() ? load_pointmap_file(existing(r.full_pointmap, "full_pointmap"))
                                                        : pointmap;
    // rejected: the occluded input; preferred: the full-object input; condition: the resampling input.
    p.neg = data::prepare_condition_inputs(rgb, mask, pointmap, pre).tensors;
    p.pos = data::prepare_condition_inputs(full_rgb, full_mask, full_pointmap, pre).tensors;
    p.cond = data::prepare_condition_inputs(rgb, mask, pointmap, pre, full_mask).tensors;
  } else {
    // Corrupted mask: must differ from the clean one.
    const auto bad = read_checked_mask(r.corrupted_mask, "corrupted_mask", r.image, H, W);
    SIMU_CHECK(!torch::equal(bad > 0, mask > 0), "corrupted_mask {} selects the same pixels as mask {}",
               r.corrupted_mask, r.mask);
    p.pos = data::prepare_condition_inputs(rgb, mask, pointmap, pre).tensors;
    p.neg = data::prepare_condition_inputs(rgb, bad, pointmap, pre).tensors;
  }
  return p;
}

}  // namespace

torch::Tensor load_pointmap_file(const std::string& path) {
  if (path.size() > 4 && path.compare(path.size() - 4, 4, ".npy") == 0) {
    auto pm = data::read_npy(path).to(torch::kFloat32);
    SIMU_CHECK(pm.dim() == 3 && pm.size(2) == 3, "{}: an .npy point map is [H, W, 3] (OpenCV camera), got [{}]", path,
               fmt::join(pm.sizes(), ", "));
    // OpenCV (x right, y down) -> PyTorch3D (x left, y up).
    pm = pm.permute({2, 0, 1}).contiguous();
    pm.slice(0, 0, 2).neg_();
    return pm;
  }
  auto file = data::SafeTensorsFile::open(path);
  const auto keys = file.keys();
  std::string key;
  for (const auto& k : keys)
    if (k == "pointmap") key = k;
  if (key.empty()) {
    SIMU_CHECK(keys.size() == 1, "{}: expected one tensor or one named 'pointmap', found {}", path, keys.size());
    key = keys[0];
  }
  auto pm = file.get(key).to(torch::kFloat32).clone();
  if (pm.dim() == 3 && pm.size(0) != 3 && pm.size(2) == 3) pm = pm.permute({2, 0, 1}).contiguous();
  SIMU_CHECK(pm.dim() == 3 && pm.size(0) == 3, "{}: '{}' has shape {}, expected [3, H, W] or [H, W, 3]", path, key,
             fmt::format("[{}]", fmt::join(pm.sizes(), ", ")));
  return pm;
}

torch::Tensor default_pointmap(int64_t height, int64_t width) {
  const double f = (width / 2.0) / std::tan(30.0 * M_PI / 180.0);
  // Pixel centres relative to the principal point (image centre), OpenCV axes, then PyTorch3D axes.
  const auto u = torch::arange(width, torch::kFloat64).add(0.5 - width / 2.0).div(f);    // [W]
  const auto v = torch::arange(height, torch::kFloat64).add(0.5 - height / 2.0).div(f);  // [H]
  const auto x = -u.unsqueeze(0).expand({height, width});
  const auto y = -v.unsqueeze(1).expand({height, width});
  const auto z = torch::ones({height, width}, torch::kFloat64);
  return torch::stack({x, y, z}).to(torch::kFloat32);  // [3, H, W]
}

uint64_t pair_noise_seed(uint64_t seed, const std::string& id) {
  uint64_t h = 0xCBF29CE484222325ULL;  // FNV-1a 64
  for (unsigned char c : id) {
    h ^= c;
    h *= 0x100000001B3ULL;
  }
  return splitmix64(seed ^ h);
}

namespace {

// The cache being built. The writer is opened on the first pair to add (a run with nothing to add
// leaves `out` untouched) and committed now and then, so a crash loses little.
class CacheSink {
 public:
  CacheSink(const PairBuilderConfig& cfg, std::vector<int64_t> latent_shape, std::vector<int64_t> cond_shape,
            PairBuildReport& report)
      : cfg_(cfg), latent_shape_(std::move(latent_shape)), cond_shape_(std::move(cond_shape)), report_(report) {}

  // Opens the writer now (its errors concern the cache, not a record).
  void ensure_open() {
    if (!writer_) open();
  }
  void append(const data::PairRecord& rec) {
    if (!writer_) open();
    writer_->append(rec);
    appended_any_ = true;
    ++report_.written;
    ++since_commit_;
  }
  // Commits when cfg.commit_every pairs were added since the last commit.
  void commit_now_and_then() {
    if (cfg_.commit_every > 0 && since_commit_ >= cfg_.commit_every) commit();
  }
  // The last commit; with nothing to add and no cache yet, an empty one so that the output exists.
  void finish() {
    commit();
    if (!std::filesystem::exists(cfg_.out) || (!cfg_.resume && !appended_any_)) {
      open();
      commit();
    }
  }

 private:
  void open() {
    const bool extend = std::filesystem::exists(cfg_.out) && (cfg_.resume || appended_any_);
    if (cfg_.cond_mode == "inputs")
      writer_ = std::make_unique<data::PairCacheWriter>(
          cfg_.out, latent_shape_, cond_shape_, cfg_.dtype,
          data::InputsLayout::storage_named(cfg_.inputs_storage, cfg_.preprocess.image_size, cfg_.preprocess.pointmap_size),
          extend);
    else
      writer_ = std::make_unique<data::PairCacheWriter>(cfg_.out, latent_shape_, cond_shape_, cfg_.dtype, extend);
    writer_->set_created_by(cfg_.created_by);
  }
  void commit() {
    if (!writer_) return;
    writer_->finish();
    report_.cache_size = writer_->size();
    writer_.reset();
    since_commit_ = 0;
  }

  const PairBuilderConfig& cfg_;
  std::vector<int64_t> latent_shape_, cond_shape_;
  PairBuildReport& report_;
  std::unique_ptr<data::PairCacheWriter> writer_;
  int64_t since_commit_ = 0;
  bool appended_any_ = false;
};

// The records still to build: those of the manifest not yet in an existing cache (resume; its
// latent and condition shapes must be the models'); the others are counted as skipped.
std::vector<PairManifestRecord> pending_records(std::vector<PairManifestRecord>& records, const PairBuilderConfig& cfg,
                                                const std::vector<int64_t>& latent_shape,
                                                const std::vector<int64_t>& cond_shape, PairBuildReport& report) {
  std::set<std::string> existing_ids;
  if (cfg.resume && std::filesystem::exists(cfg.out)) {
    const auto reader = data::PairCacheReader::open(cfg.out);
    for (auto& id : reader.ids()) existing_ids.insert(std::move(id));
    SIMU_CHECK(reader.info().latent_shape == latent_shape && reader.info().cond_shape == cond_shape,
               "build_pairs: existing cache {} has latents [{}, {}] and cond [{}, {}], these models give [{}, {}] and "
               "[{}, {}] (use another --out, or --overwrite)",
               cfg.out, reader.info().latent_shape[0], reader.info().latent_shape[1], reader.info().cond_shape[0],
               reader.info().cond_shape[1], latent_shape[0], latent_shape[1], cond_shape[0], cond_shape[1]);
    SIMU_CHECK(reader.info().cond_mode == cfg.cond_mode,
               "build_pairs: existing cache {} stores cond_mode {}, this run writes {} (use another --out, or --overwrite)",
               cfg.out, reader.info().cond_mode, cfg.cond_mode);
  }
  std::vector<PairManifestRecord> todo;
  for (auto& r : records) {
    if (existing_ids.count(r.id))
      ++report.skipped_existing;
    else
      todo.push_back(std::move(r));
  }
  return todo;
}

// Condition tokens of every side of a batch (and of every resampling condition), from ONE embedder
// call: tokens[pos[k]], tokens[neg[k]] and tokens[cond[k]] belong to pair k ([L, Cc], CPU float32).
// with_cond false (inputs mode: the cache stores the condition's inputs): the resampling conditions
// are not embedded (cond[k] is unset).
struct BatchTokens {
  std::vector<torch::Tensor> tokens;
  std::vector<size_t> pos, neg, cond;
};
BatchTokens embed_batch(Resampler& resampler, const std::vector<PreparedPair>& batch, bool with_cond) {
  BatchTokens bt;
  std::vector<ResampleRequest> requests;
  bt.pos.resize(batch.size()), bt.neg.resize(batch.size()), bt.cond.resize(batch.size());
  for (size_t k = 0; k < batch.size(); ++k) {
    bt.pos[k] = requests.size();
    requests.push_back({torch::Tensor(), batch[k].pos});
    bt.neg[k] = requests.size();
    requests.push_back({torch::Tensor(), batch[k].neg});
    bt.cond[k] = bt.pos[k];
    if (with_cond && !batch[k].cond.empty()) {
      bt.cond[k] = requests.size();
      requests.push_back({torch::Tensor(), batch[k].cond});
    }
  }
  bt.tokens = resampler.conditions(requests);
  return bt;
}

// Stage 1 on both sides of every pair of a batch: rows (pos_k, neg_k) share pair k's noise (seeded by
// (seed, id)); one sampling call per condition length. Shape latents [T, C] float32 CPU per pair.
// With sample_pos false only the x- rows are sampled (shape_pos stays undefined).
void sample_both_sides(Resampler& resampler, const PairBuilderConfig& cfg, const std::vector<PreparedPair>& batch,
                       const BatchTokens& bt, std::vector<torch::Tensor>* shape_pos,
                       std::vector<torch::Tensor>* shape_neg, bool sample_pos = true) {
  auto& gen = resampler.generator();
  const auto options = resampler.sample_options();
  const auto device = resampler.device();
  shape_pos->assign(batch.size(), torch::Tensor());
  shape_neg->assign(batch.size(), torch::Tensor());
  std::map<int64_t, std::vector<std::pair<size_t, bool>>> groups;  // L -> (pair, is_pos)
  for (size_t k = 0; k < batch.size(); ++k) {
    if (sample_pos) groups[bt.tokens[bt.pos[k]].size(0)].push_back({k, true});
    groups[bt.tokens[bt.neg[k]].size(0)].push_back({k, false});
  }
  std::vector<models::Latents> noise(batch.size());
  for (size_t k = 0; k < batch.size(); ++k) {
    auto rng = at::make_generator<at::CPUGeneratorImpl>(pair_noise_seed(cfg.seed, batch[k].record.id));
    noise[k] = gen->noise(1, rng, torch::kCPU);
  }
  torch::NoGradGuard no_grad;
  for (const auto& [L, rows] : groups) {
    std::vector<torch::Tensor> conds;
    std::map<std::string, std::vector<torch::Tensor>> x0_parts;
    for (const auto& [k, is_pos] : rows) {
      conds.push_back(bt.tokens[is_pos ? bt.pos[k] : bt.neg[k]].to(torch::kFloat32).unsqueeze(0));
      for (const auto& [name, v] : noise[k]) x0_parts[name].push_back(v);
    }
    models::Latents x0;
    for (auto& [name, parts] : x0_parts) x0[name] = torch::cat(parts, 0).to(device);
    const auto latents = gen->sample(torch::cat(conds, 0).to(device), x0, options);
    const auto shape = latents.at("shape").to(torch::kCPU, torch::kFloat32);  // [rows, T, C]
    for (size_t j = 0; j < rows.size(); ++j)
      (rows[j].second ? *shape_pos : *shape_neg)[rows[j].first] = shape[static_cast<int64_t>(j)].clone();
  }
}

// A bad manifest record: logged with its line and kept in the report (the record is skipped).
void add_pair_issue(PairBuildReport& report, const std::string& manifest_path, int64_t line, const std::string& id,
                    const std::string& message) {
  simu::log::warn("{}:{}: {}skipped: {}", manifest_path, line, id.empty() ? "" : "pair '" + id + "' ", message);
  report.issues.push_back({line, id, message});
}

// PairBuilderConfig::preferred == "gt_latent": x+ of every pair is the encoder's posterior mean of its
// record's gt_occupancy, as tokens [k^3, C] (token t = (x k + y) k + z of the grid [C, k, k, k], the
// order models::shape_tokens_to_grid reads). A record without a usable ground truth is an issue
// (shape_pos stays undefined: append_batch skips it).
void gt_latents(models::SparseStructureEncoderImpl& encoder, const std::vector<PreparedPair>& batch,
                const std::vector<int64_t>& latent_shape, std::vector<torch::Tensor>& shape_pos,
                const std::string& manifest_path, PairBuildReport& report) {
  const int64_t R = encoder.config().downsample_factor() * int64_t(std::llround(std::cbrt(double(latent_shape[0]))));
  std::vector<size_t> rows;
  std::vector<torch::Tensor> occ;
  for (size_t k = 0; k < batch.size(); ++k) {
    const auto& r = batch[k].record;
    shape_pos[k] = torch::Tensor();
    try {
      SIMU_CHECK(!r.gt_occupancy.empty(), "x+ from the ground truth needs 'gt_occupancy' (build_pairs --preferred gt-latent)");
      auto gt = data::read_npy(r.gt_occupancy);
      SIMU_CHECK(gt.dim() == 3 && gt.size(0) == R && gt.size(1) == R && gt.size(2) == R,
                 "gt_occupancy {} is [{}], the encoder reads [{}, {}, {}]", r.gt_occupancy, fmt::join(gt.sizes(), ", "), R, R, R);
      occ.push_back(gt.ne(0).to(torch::kFloat32).unsqueeze(0));  // [1, R, R, R]
      rows.push_back(k);
    } catch (const std::exception& e) {
      add_pair_issue(report, manifest_path, r.line, r.id, e.what());
    }
  }
  if (rows.empty()) return;
  torch::NoGradGuard no_grad;
  const auto device = encoder.input_layer->weight.device();
  const auto mean = encoder.posterior(torch::stack(occ, 0).to(device)).first;  // [n, C, k, k, k]
  const auto tokens = mean.reshape({mean.size(0), mean.size(1), -1}).permute({0, 2, 1}).to(torch::kCPU).contiguous();
  SIMU_CHECK(tokens.size(1) == latent_shape[0] && tokens.size(2) == latent_shape[1],
             "build_pairs: the encoder's latent is [{}, {}] tokens, the generator's shape latent [{}, {}]", tokens.size(1),
             tokens.size(2), latent_shape[0], latent_shape[1]);
  for (size_t j = 0; j < rows.size(); ++j) shape_pos[rows[j]] = tokens[int64_t(j)].clone();
}

// The paper's filter (PairBuilderConfig::filter_gt): both sides of every pair decoded in one call, each
// occupancy (logits > 0) compared with the record's ground truth by IoU; a pair is kept when x+ is
// the closer one. Dropped pairs (and records without a usable ground truth, reported as issues) get
// an undefined shape_pos, which append_batch skips.
void filter_batch(Resampler& resampler, const std::vector<PreparedPair>& batch, std::vector<torch::Tensor>& shape_pos,
                  const std::vector<torch::Tensor>& shape_neg, const std::string& manifest_path, PairBuildReport& report) {
  std::vector<size_t> judged;
  std::vector<torch::Tensor> gts;
  for (size_t k = 0; k < batch.size(); ++k) {
    const auto& r = batch[k].record;
    if (!shape_pos[k].defined()) continue;  // no x+ (already reported)
    try {
      SIMU_CHECK(!r.gt_occupancy.empty(), "the filter needs 'gt_occupancy' (build_pairs --filter-gt)");
      auto gt = data::read_npy(r.gt_occupancy);
      SIMU_CHECK(gt.dim() == 3 && gt.size(0) == gt.size(1) && gt.size(1) == gt.size(2),
                 "gt_occupancy {} is [{}], expected [R, R, R]", r.gt_occupancy, fmt::join(gt.sizes(), ", "));
      gts.push_back(gt.ne(0));
      judged.push_back(k);
    } catch (const std::exception& e) {
      add_pair_issue(report, manifest_path, r.line, r.id, e.what());
      shape_pos[k] = torch::Tensor();
    }
  }
  if (judged.empty()) return;
  std::vector<torch::Tensor> lat;
  for (size_t k : judged) lat.push_back(shape_pos[k]);
  for (size_t k : judged) lat.push_back(shape_neg[k]);
  torch::NoGradGuard no_grad;
  const auto occ = resampler.decode_logits(torch::stack(lat, 0).to(resampler.device())).gt(0).to(torch::kCPU);  // [2n, 1, R, R, R]
  const int64_t n = static_cast<int64_t>(judged.size());
  for (int64_t j = 0; j < n; ++j) {
    const size_t k = judged[static_cast<size_t>(j)];
    const auto& r = batch[k].record;
    const auto& gt = gts[static_cast<size_t>(j)];
    const int64_t G = gt.size(0), R = occ.size(2);
    if (G > R || R % G != 0) {
      add_pair_issue(report, manifest_path, r.line, r.id,
                     fmt::format("gt_occupancy {} is {}^3, the decoder makes {}^3 (the truth's side must divide it)",
                                 r.gt_occupancy, G, R));
      shape_pos[k] = torch::Tensor();
      continue;
    }
    // A decoded grid on the truth's side: a coarse voxel is occupied when any of its (R/G)^3 fine ones is
    // (as the conservative filled voxelisation marks it; eval_lift --shape-grid pools the same way).
    auto on_gt_side = [&](const torch::Tensor& a) {  // [R, R, R] bool -> [G, G, G] bool
      if (G == R) return a;
      return torch::max_pool3d(a.to(torch::kFloat32).unsqueeze(0), R / G).squeeze(0).gt(0);
    };
    // IoU of two boolean grids (two empty grids agree: 1).
    auto iou = [&](const torch::Tensor& a) {
      const auto p = on_gt_side(a);
      const double uni = (p | gt).sum().item<double>();
      return uni == 0 ? 1.0 : (p & gt).sum().item<double>() / uni;
    };
    PairFilterRow row{r.id, r.kind, iou(occ[j][0]), iou(occ[n + j][0]), false};
    row.kept = row.iou_pos > row.iou_neg;
    if (!row.kept) shape_pos[k] = torch::Tensor();
    report.filtered.push_back(row);
  }
}

// Appends the pairs of a sampled batch to the cache (a non-finite output is a bad record, not a
// broken cache).
void append_batch(const std::vector<PreparedPair>& batch, const BatchTokens& bt, const std::vector<torch::Tensor>& shape_pos,
                  const std::vector<torch::Tensor>& shape_neg, const std::string& manifest_path, CacheSink& sink,
                  PairBuildReport& report, bool inputs_mode) {
  for (size_t k = 0; k < batch.size(); ++k) {
    const auto& r = batch[k].record;
    if (!shape_pos[k].defined()) continue;  // dropped by the filter
    data::PairRecord rec;
    rec.id = r.id;
    rec.kind = r.kind;
    rec.weight = r.weight;
    rec.latent_pos = shape_pos[k];
    rec.latent_neg = shape_neg[k];
    if (inputs_mode) {
      // The resampling condition's preprocessed inputs ([1, ch, S, S] each; the clean input for kind 1).
      for (const auto& [name, t] : batch[k].cond.empty() ? batch[k].pos : batch[k].cond) rec.inputs[name] = t[0];
    } else {
      rec.cond = bt.tokens[bt.cond[k]];
    }
    if (!(torch::isfinite(rec.latent_pos).all().item<bool>() && torch::isfinite(rec.latent_neg).all().item<bool>() &&
          (inputs_mode || torch::isfinite(rec.cond).all().item<bool>()))) {
      add_pair_issue(report, manifest_path, r.line, r.id, "the models produced non-finite latents or condition tokens");
      continue;
    }
    sink.ensure_open();
    try {
      sink.append(rec);  // checks the whole record before writing: a refused one leaves the cache as it was
    } catch (const data::RecordRefused& e) {
      // e.g. inputs mode: a 16-bit mask (not an 8-bit level) or an image far outside [0, 1].
      add_pair_issue(report, manifest_path, r.line, r.id, e.what());
    }
  }
}

}  // namespace

PairBuildReport build_pairs(const std::string& manifest_path, const PairBuilderConfig& cfg, Resampler& resampler,
                            const PairBuildProgress& progress, const std::atomic<bool>* stop) {
  const auto t_start = std::chrono::steady_clock::now();
  SIMU_CHECK(!cfg.out.empty(), "build_pairs: no output path");
  SIMU_CHECK(cfg.batch > 0, "build_pairs: batch must be positive, got {}", cfg.batch);
  SIMU_CHECK(cfg.dtype == torch::kFloat16 || cfg.dtype == torch::kFloat32, "build_pairs: dtype must be float16 or float32");
  SIMU_CHECK(resampler.embedder(), "build_pairs: the resampler has no condition embedder (set embedder_config)");
  SIMU_CHECK(cfg.cond_mode == "tokens" || cfg.cond_mode == "inputs", "build_pairs: cond_mode '{}' (expected tokens or inputs)",
             cfg.cond_mode);
  if (cfg.cond_mode == "inputs")  // the storage's sizes must be known before the first pair
    (void)data::InputsLayout::storage_named(cfg.inputs_storage, cfg.preprocess.image_size, cfg.preprocess.pointmap_size);
  PairBuildReport report;

  // Manifest: parse every line; malformed ones and duplicate ids become issues.
  auto manifest = parse_manifest(simu::fs::read_file(manifest_path),
                                 std::filesystem::path(manifest_path).parent_path().string());
  report.records = manifest.records;
  auto add_issue = [&](int64_t line, const std::string& id, const std::string& message) {
    add_pair_issue(report, manifest_path, line, id, message);
  };
  for (const auto& issue : manifest.issues) add_issue(issue.line, issue.id, issue.message);

  // Shapes of what the models produce: latent [T, C] and condition [L, Cc].
  auto shape_gen = at::make_generator<at::CPUGeneratorImpl>(0);
  const auto probe_noise = resampler.generator()->noise(1, shape_gen, torch::kCPU);
  SIMU_CHECK(probe_noise.count("shape"), "build_pairs: the generator has no 'shape' latent");
  const std::vector<int64_t> latent_shape{probe_noise.at("shape").size(1), probe_noise.at("shape").size(2)};
  const std::vector<int64_t> cond_shape{resampler.embedder()->num_tokens(), resampler.embedder()->embed_dims()};

  // x+ from the ground truth: the frozen encoder, checked against the generator's shape latent.
  SIMU_CHECK(cfg.preferred == "sample" || cfg.preferred == "gt_latent", "build_pairs: preferred '{}' (sample, gt_latent)",
             cfg.preferred);
  const bool from_gt = cfg.preferred == "gt_latent";
  models::SparseStructureEncoder encoder{nullptr};
  if (from_gt) {
    SIMU_CHECK(!cfg.encoder_config.empty() && !cfg.encoder_weights.empty(),
               "build_pairs: x+ from the ground truth needs the encoder (--encoder-config and --encoder-weights, a "
               "train_ss_vae output's weights/ss_encoder.*)");
    encoder = models::load_ss_encoder(cfg.encoder_config, cfg.encoder_weights, resampler.device());
    encoder->eval();
    const int64_t k = int64_t(std::llround(std::cbrt(double(latent_shape[0]))));
    SIMU_CHECK(k * k * k == latent_shape[0] && encoder->config().latent_channels == latent_shape[1],
               "build_pairs: encoder {} makes [{}, k^3] latents; the generator's shape latent is [{} tokens, {}]",
               cfg.encoder_config, encoder->config().latent_channels, latent_shape[0], latent_shape[1]);
  }

  const std::vector<PairManifestRecord> todo = pending_records(manifest.pairs, cfg, latent_shape, cond_shape, report);
  simu::log::info("build_pairs: {} records in {}, {} already in {}, {} to build, {} bad so far", report.records,
                  manifest_path, report.skipped_existing, cfg.out, todo.size(), report.issues.size());
  PairBuilderConfig sink_cfg = cfg;
  if (from_gt) sink_cfg.created_by += " [x+ = ground-truth encoder latent: build_pairs --preferred gt-latent]";
  CacheSink sink(sink_cfg, latent_shape, cond_shape, report);
  int64_t done = static_cast<int64_t>(report.issues.size()) + report.skipped_existing;
  const int64_t total = report.records;
  if (progress) progress(done, total);
  for (size_t b0 = 0; b0 < todo.size(); b0 += static_cast<size_t>(cfg.batch)) {
    if (stop && stop->load()) {
      report.interrupted = true;
      break;
    }
    const size_t b1 = std::min(todo.size(), b0 + static_cast<size_t>(cfg.batch));
    // Files -> preprocessed inputs per side; bad records are reported and dropped.
    std::vector<PreparedPair> batch;
    for (size_t i = b0; i < b1; ++i) {
      try {
        batch.push_back(prepare_pair(todo[i], cfg.preprocess));
      } catch (const std::exception& e) {
        add_issue(todo[i].line, todo[i].id, e.what());
        ++done;
      }
    }
    if (batch.empty()) {
      if (progress) progress(done, total);
      continue;
    }
    const bool inputs_mode = cfg.cond_mode == "inputs";
    const BatchTokens bt = embed_batch(resampler, batch, !inputs_mode);
    std::vector<torch::Tensor> shape_pos, shape_neg;
    sample_both_sides(resampler, cfg, batch, bt, &shape_pos, &shape_neg, !from_gt);
    if (from_gt) gt_latents(*encoder, batch, latent_shape, shape_pos, manifest_path, report);
    if (cfg.filter_gt) filter_batch(resampler, batch, shape_pos, shape_neg, manifest_path, report);
    append_batch(batch, bt, shape_pos, shape_neg, manifest_path, sink, report, inputs_mode);
    done += static_cast<int64_t>(batch.size());
    if (progress) progress(done, total);
    sink.commit_now_and_then();
  }
  sink.finish();
  if (report.cache_size == 0 && std::filesystem::exists(cfg.out))
    report.cache_size = data::PairCacheReader::open(cfg.out).size();
  std::sort(report.issues.begin(), report.issues.end(),
            [](const PairIssue& a, const PairIssue& b) { return a.line < b.line; });
  report.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count();
  return report;
}

PairBuildReport build_pairs(const std::string& manifest_path, const PairBuilderConfig& cfg,
                            const PairBuildProgress& progress, const std::atomic<bool>* stop) {
  SIMU_CHECK(!cfg.resampler.embedder_config.empty(), "build_pairs {}: the condition embedder config is required",
             manifest_path);
  auto rc = cfg.resampler;
  rc.num_samples = 1;
  rc.use_decoder = cfg.filter_gt;  // latents only, unless the filter decodes them
  Resampler resampler(rc);
  return build_pairs(manifest_path, cfg, resampler, progress, stop);
}

}  // namespace simu::resample
