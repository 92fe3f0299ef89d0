#include "resample/pair_builder.h"

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

PairBuildReport build_pairs(const std::string& manifest_path, const PairBuilderConfig& cfg, Resampler& resampler,
                            const PairBuildProgress& progress, const std::atomic<bool>* stop) {
  const auto t_start = std::chrono::steady_clock::now();
  SIMU_CHECK(!cfg.out.empty(), "build_pairs: no output path");
  SIMU_CHECK(cfg.batch > 0, "build_pairs: batch must be positive, got {}", cfg.batch);
  SIMU_CHECK(cfg.dtype == torch::kFloat16 || cfg.dtype == torch::kFloat32, "build_pairs: dtype must be float16 or float32");
  SIMU_CHECK(resampler.embedder(), "build_pairs: the resampler has no condition embedder (set embedder_config)");
  PairBuildReport report;

  // Manifest: parse every line; malformed ones and duplicate ids become issues.
  auto manifest = parse_manifest(simu::fs::read_file(manifest_path),
                                 std::filesystem::path(manifest_path).parent_path().string());
  report.records = manifest.records;
  auto add_issue = [&](int64_t line, const std::string& id, const std::string& message) {
    simu::log::warn("{}:{}: {}skipped: {}", manifest_path, line, id.empty() ? "" : "pair '" + id + "' ", message);
    report.issues.push_back({line, id, message});
  };
  for (const auto& issue : manifest.issues) add_issue(issue.line, issue.id, issue.message);
  auto& records = manifest.pairs;

  // Shapes of what the models produce: latent [T, C] and condition [L, Cc].
  auto& gen = resampler.generator();
  auto shape_gen = at::make_generator<at::CPUGeneratorImpl>(0);
  const auto probe_noise = gen->noise(1, shape_gen, torch::kCPU);
  SIMU_CHECK(probe_noise.count("shape"), "build_pairs: the generator has no 'shape' latent");
  const std::vector<int64_t> latent_shape{probe_noise.at("shape").size(1), probe_noise.at("shape").size(2)};
  const std::vector<int64_t> cond_shape{resampler.embedder()->num_tokens(), resampler.embedder()->embed_dims()};

  // Already written pairs (resume): read the ids of an existing cache.
  std::set<std::string> existing_ids;
  const bool have_out = std::filesystem::exists(cfg.out);
  if (cfg.resume && have_out) {
    const auto reader = data::PairCacheReader::open(cfg.out);
    for (auto& id : reader.ids()) existing_ids.insert(std::move(id));
    SIMU_CHECK(reader.info().latent_shape == latent_shape && reader.info().cond_shape == cond_shape,
               "build_pairs: existing cache {} has latents [{}, {}] and cond [{}, {}], these models give [{}, {}] and "
               "[{}, {}] (use another --out, or --overwrite)",
               cfg.out, reader.info().latent_shape[0], reader.info().latent_shape[1], reader.info().cond_shape[0],
               reader.info().cond_shape[1], latent_shape[0], latent_shape[1], cond_shape[0], cond_shape[1]);
  }
  std::vector<PairManifestRecord> todo;
  for (auto& r : records) {
    if (existing_ids.count(r.id))
      ++report.skipped_existing;
    else
      todo.push_back(std::move(r));
  }
  simu::log::info("build_pairs: {} records in {}, {} already in {}, {} to build, {} bad so far", report.records,
                  manifest_path, report.skipped_existing, cfg.out, todo.size(), report.issues.size());

  // The writer is opened on the first pair to add (a run with nothing to add leaves `out` untouched).
  std::unique_ptr<data::PairCacheWriter> writer;
  int64_t since_commit = 0;
  bool appended_any = false;
  auto open_writer = [&] {
    const bool extend = std::filesystem::exists(cfg.out) && (cfg.resume || appended_any);
    writer = std::make_unique<data::PairCacheWriter>(cfg.out, latent_shape, cond_shape, cfg.dtype, extend);
    writer->set_created_by(cfg.created_by);
  };
  auto commit = [&] {
    if (!writer) return;
    writer->finish();
    report.cache_size = writer->size();
    writer.reset();
    since_commit = 0;
  };

  int64_t done = static_cast<int64_t>(report.issues.size()) + report.skipped_existing;
  const int64_t total = report.records;
  if (progress) progress(done, total);
  const auto options = resampler.sample_options();
  const auto device = resampler.device();

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
    // Condition tokens of every side (and of every resampling condition) in one embedder call.
    std::vector<ResampleRequest> requests;
    std::vector<size_t> pos_req(batch.size()), neg_req(batch.size()), cond_req(batch.size());
    for (size_t k = 0; k < batch.size(); ++k) {
      pos_req[k] = requests.size();
      requests.push_back({torch::Tensor(), batch[k].pos});
      neg_req[k] = requests.size();
      requests.push_back({torch::Tensor(), batch[k].neg});
      cond_req[k] = pos_req[k];
      if (!batch[k].cond.empty()) {
        cond_req[k] = requests.size();
        requests.push_back({torch::Tensor(), batch[k].cond});
      }
    }
    const auto tokens = resampler.conditions(requests);  // [L, Cc] each, CPU float32

    // Stage 1 on both sides: rows (pos_k, neg_k) share pair k's noise; one call per condition length.
    std::vector<torch::Tensor> shape_pos(batch.size()), shape_neg(batch.size());
    std::map<int64_t, std::vector<std::pair<size_t, bool>>> groups;  // L -> (pair, is_pos)
    for (size_t k = 0; k < batch.size(); ++k) {
      groups[tokens[pos_req[k]].size(0)].push_back({k, true});
      groups[tokens[neg_req[k]].size(0)].push_back({k, false});
    }
    std::vector<models::Latents> noise(batch.size());
    for (size_t k = 0; k < batch.size(); ++k) {
      auto rng = at::make_generator<at::CPUGeneratorImpl>(pair_noise_seed(cfg.seed, batch[k].record.id));
      noise[k] = gen->noise(1, rng, torch::kCPU);
    }
    {
      torch::NoGradGuard no_grad;
      for (const auto& [L, rows] : groups) {
        std::vector<torch::Tensor> conds;
        std::map<std::string, std::vector<torch::Tensor>> x0_parts;
        for (const auto& [k, is_pos] : rows) {
          conds.push_back(tokens[is_pos ? pos_req[k] : neg_req[k]].to(torch::kFloat32).unsqueeze(0));
          for (const auto& [name, v] : noise[k]) x0_parts[name].push_back(v);
        }
        models::Latents x0;
        for (auto& [name, parts] : x0_parts) x0[name] = torch::cat(parts, 0).to(device);
        const auto latents = gen->sample(torch::cat(conds, 0).to(device), x0, options);
        const auto shape = latents.at("shape").to(torch::kCPU, torch::kFloat32);  // [rows, T, C]
        for (size_t j = 0; j < rows.size(); ++j)
          (rows[j].second ? shape_pos : shape_neg)[rows[j].first] = shape[static_cast<int64_t>(j)].clone();
      }
    }

    // Append (a non-finite output is a bad record, not a broken cache).
    for (size_t k = 0; k < batch.size(); ++k) {
      const auto& r = batch[k].record;
      data::PairRecord rec;
      rec.id = r.id;
      rec.kind = r.kind;
      rec.weight = r.weight;
      rec.latent_pos = shape_pos[k];
      rec.latent_neg = shape_neg[k];
      rec.cond = tokens[cond_req[k]];
      ++done;
      if (!(torch::isfinite(rec.latent_pos).all().item<bool>() && torch::isfinite(rec.latent_neg).all().item<bool>() &&
            torch::isfinite(rec.cond).all().item<bool>())) {
        add_issue(r.line, r.id, "the models produced non-finite latents or condition tokens");
        continue;
      }
      if (!writer) open_writer();
      writer->append(rec);
      appended_any = true;
      ++report.written;
      ++since_commit;
    }
    if (progress) progress(done, total);
    // Commit now and then so a crash loses little.
    if (cfg.commit_every > 0 && since_commit >= cfg.commit_every) commit();
  }
  commit();
  // Nothing to add and no cache yet: write an empty one so the output exists.
  if (!std::filesystem::exists(cfg.out) || (!cfg.resume && !appended_any)) {
    open_writer();
    commit();
  }
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
  rc.use_decoder = false;  // latents only
  Resampler resampler(rc);
  return build_pairs(manifest_path, cfg, resampler, progress, stop);
}

}  // namespace simu::resample
