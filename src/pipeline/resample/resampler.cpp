#include "pipeline/resample/resampler.h"

#include "pipeline/resample/default_model.h"

#include <ATen/CPUGeneratorImpl.h>
#include <ATen/Parallel.h>

#include <mutex>
#include <optional>
#include <fmt/format.h>
#include <fmt/ranges.h>

#include <chrono>
#include <cmath>
#include <map>

#include "common/error.h"
#include "common/log.h"
#include "common/random.h"
#include "common/timing.h"
#include "lora/lora.h"
#include "models/weights.h"

namespace simu::resample {

namespace {
// A sanity bound on ResamplerConfig::empty_retries: each retry is one more sampling of the empty rows.
constexpr int kMaxEmptyRetries = 100;
constexpr const char* kNoOccupiedVoxel = "no occupied voxel (every logit <= 0)";

void sync(const torch::Device& d) {
  if (d.is_cuda()) torch::cuda::synchronize(d.index() < 0 ? 0 : d.index());
}
torch::Device pick_device(const std::string& name) {
  if (name == "auto") return torch::cuda::is_available() ? torch::Device(torch::kCUDA, 0) : torch::Device(torch::kCPU);
  torch::Device d(name);
  SIMU_CHECK(!d.is_cuda() || torch::cuda::is_available(), "resampler: device '{}' requested but no CUDA device is present",
             name);
  return d;
}
}  // namespace

ResamplerConfig ResamplerConfig::from(simu::config::Reader& r) {
  ResamplerConfig c;
  r.field("generator_config", c.generator_config);
  r.field("generator_weights", c.generator_weights);
  r.field("decoder_config", c.decoder_config);
  r.field("decoder_weights", c.decoder_weights);
  r.field("adapter_dir", c.adapter_dir);
  r.field("generator_overrides", c.generator_overrides);
  r.field("embedder_config", c.embedder_config);
  r.field("embedder_weights", c.embedder_weights);
  r.field("preprocess", c.preprocess);
  r.field("random_weights", c.random_weights);
  r.field("device", c.device);
  r.field("steps", c.steps);
  r.field("rescale_t", c.rescale_t);
  r.field("cfg_strength", c.cfg_strength);
  r.field("surface_offset", c.surface_offset);
  if (r.has("cfg_interval")) {
    const auto v = r.require<std::vector<double>>("cfg_interval");
    SIMU_CHECK(v.size() == 2, "{}: cfg_interval must be [lo, hi], got {} values", r.file(), v.size());
    c.cfg_interval = {v[0], v[1]};
  }
  r.field("shortcut", c.shortcut);
  r.field("solver", c.solver);
  SIMU_CHECK(c.solver.empty() || c.solver == "euler" || c.solver == "midpoint" || c.solver == "rk4",
             "{}: solver must be euler, midpoint or rk4 (or absent: the generator config's), got '{}'", r.file(), c.solver);
  r.field("precision", c.precision);
  if (r.has("bf16")) {  // the earlier switch: bf16 true -> bf16, false -> fp32
    c.precision = r.require<bool>("bf16") ? "bf16" : "fp32";
  }
  r.field("cuda_graphs", c.cuda_graphs);
  if (r.has("step_cache")) {
    auto sc = r.child("step_cache");
    auto& o = c.step_cache;
    sc.field("enabled", o.enabled), sc.field("interval", o.interval), sc.field("order", o.order);
    sc.field("warmup", o.warmup), sc.field("tail", o.tail), sc.field("pose_momentum", o.pose_momentum);
    sc.field("tolerance", o.tolerance);
    o.validate(r.file() + ": step_cache.");
  }
  r.field("num_samples", c.num_samples);
  r.field("empty_retries", c.empty_retries);
  r.field("decode_batch", c.decode_batch);
  r.field("pose_convention", c.pose_convention);
  r.finish();
  SIMU_CHECK(c.steps > 0 && c.num_samples > 0 && c.decode_batch > 0,
             "{}: steps, num_samples and decode_batch must be positive", r.file());
  SIMU_CHECK(c.empty_retries >= 0 && c.empty_retries <= kMaxEmptyRetries,
             "{}: empty_retries must be in [0, {}], got {}", r.file(), kMaxEmptyRetries, c.empty_retries);
  return c;
}

namespace {
// Seeds torch's default CPU generator with kRandomWeightsSeed and restores its state when it goes out
// of scope: random initialisation that does not depend on what the process drew before.
class RandomInitSeed {
 public:
  RandomInitSeed() : gen_(at::detail::getDefaultCPUGenerator()) {
    std::lock_guard<std::mutex> lock(gen_.mutex());
    state_ = gen_.get_state();
    gen_.set_current_seed(kRandomWeightsSeed);
  }
  ~RandomInitSeed() {
    std::lock_guard<std::mutex> lock(gen_.mutex());
    gen_.set_state(state_);
  }
  RandomInitSeed(const RandomInitSeed&) = delete;
  RandomInitSeed& operator=(const RandomInitSeed&) = delete;

 private:
  at::Generator gen_;
  at::Tensor state_;
};
}  // namespace

void Resampler::set_adapter_enabled(bool enabled) {
  if (has_adapter_) simu::lora::set_lora_enabled(*generator_, enabled);
}

void Resampler::load_adapter(const std::string& dir) {
  simu::lora::load_peft(dir, *generator_);
  generator_->to(device_);
  generator_->eval();
  config_.adapter_dir = dir;
  has_adapter_ = true;
  simu::log::info("resampler: adapter {} loaded", dir);
}

Resampler::Resampler(ResamplerConfig config, AdapterLoader adapter_loader)
    : config_(std::move(config)), device_(pick_device(config_.device)) {
  // No weights at all: the shipped miniature (default_model.h), unless --random-weights.
  shipped_note_ = apply_shipped_model(config_);
  if (std::isnan(config_.surface_offset)) config_.surface_offset = 0.0;  // not the shipped model: none
  SIMU_CHECK(config_.surface_offset >= 0 && config_.surface_offset <= 2,
             "resampler: surface_offset {} voxels is outside [0, 2]", config_.surface_offset);
  precision_ = models::parse_precision(config_.precision, device_, "resampler precision");
  models::check_precision(precision_, device_, "resampler precision");
  // Weights: a missing file is an error naming its flag, unless random weights were asked for.
  std::vector<std::string> missing;
  if (config_.generator_weights.empty()) missing.push_back("--generator-weights (generator_weights)");
  if (config_.decoder_weights.empty() && config_.use_decoder) missing.push_back("--decoder-weights (decoder_weights)");
  if (!config_.embedder_config.empty() && config_.embedder_weights.empty())
    missing.push_back("--embedder-weights (embedder_weights)");
  if (!missing.empty()) {
    if (!config_.random_weights)
      fail_hint("convert the released checkpoints (checkpoints/README.md) and pass them; --random-weights runs "
                "without them (benchmarks and demos only: the shapes are meaningless)",
                "resampler: no weights given for {}", fmt::join(missing, ", "));
    random_banner_ = fmt::format("RANDOM WEIGHTS (--random-weights): {} not given; outputs are meaningless",
                                 fmt::join(missing, ", "));
    simu::log::warn("{}", random_banner_);
  }
  // Random init from a fixed seed (torch's CPU generator restored at the end of the constructor).
  std::optional<RandomInitSeed> seeded;
  if (!missing.empty()) seeded.emplace();
  // Generator (official names), then the adapter on top of the base weights.
  generator_ = models::load_generator(config_.generator_config, config_.generator_weights, device_,
                                      config_.generator_overrides);
  if (!config_.adapter_dir.empty()) {
    if (adapter_loader)
      adapter_loader(config_.adapter_dir, *generator_);
    else
      simu::lora::load_peft(config_.adapter_dir, *generator_);
    generator_->to(device_);
    generator_->eval();
    has_adapter_ = true;
  }
  // Sparse-structure decoder.
  models::SparseStructureDecoder decoder(models::SSDecoderConfig::load(config_.decoder_config));
  if (!config_.decoder_weights.empty()) {
    models::LoadOptions opt;
    opt.ignore_prefixes = {"io."};
    opt.source = config_.decoder_weights;
    models::load_safetensors_into(*decoder, config_.decoder_weights, opt);
  }
  decoder->to(device_);
  decoder->eval();
  decoder_ = decoder;
  // Condition embedder (optional).
  if (!config_.embedder_config.empty()) {
    embedder_ = models::load_cond_embedder(config_.embedder_config, config_.embedder_weights, "auto", device_);
    SIMU_CHECK(embedder_->embed_dims() == generator_->config().backbone.cond_channels,
               "resampler: embedder {} gives {} channels, the generator expects {}", config_.embedder_config,
               embedder_->embed_dims(), generator_->config().backbone.cond_channels);
  }
  // The decoder must read what the generator writes.
  const auto& shape = generator_->config().backbone.latent("shape");
  SIMU_CHECK(shape.in_channels == decoder_->config().latent_channels,
             "resampler: generator shape latent has {} channels, decoder {} expects {}", shape.in_channels,
             config_.decoder_config, decoder_->config().latent_channels);
  simu::log::info("resampler ready on {} in {} (generator {}, decoder {}{}; meshes moved {} voxels inward)", device_.str(),
                  models::precision_name(precision_), config_.generator_config, config_.decoder_config,
                  has_adapter_ ? ", adapter " + config_.adapter_dir : "", config_.surface_offset);
  simu::log::info("resampler sampler: {}; step caching {}",
                  models::describe_sampler(sample_options(), generator_->config(), sampler_overrides()),
                  config_.step_cache.describe());
}

models::SamplerOverrides Resampler::sampler_overrides() const {
  // The config's sampler fields default to the official inference values; the ones that differ are
  // the user's explicit choices (a released ss_generator.yaml's training-time values never enter).
  const ResamplerConfig official;
  models::SamplerOverrides u;
  if (config_.steps != official.steps) u.steps = config_.steps;
  if (config_.rescale_t != official.rescale_t) u.rescale_t = config_.rescale_t;
  if (config_.cfg_strength != official.cfg_strength) u.cfg_strength = config_.cfg_strength;
  if (config_.cfg_interval != official.cfg_interval) u.cfg_interval = config_.cfg_interval;
  if (config_.shortcut != official.shortcut) u.shortcut = config_.shortcut;
  if (!config_.solver.empty()) u.solver = config_.solver;
  return u;
}

models::SampleOptions Resampler::sample_options() const {
  models::SampleOptions o = models::official_inference_options(generator_->config(), sampler_overrides());
  // With shortcut on, the CFG strength is the configured one (7 unless changed), as before.
  o.cfg_strength = config_.cfg_strength;
  o.precision = precision_;
  o.cuda_graphs = config_.cuda_graphs;
  o.step_cache = config_.step_cache;
  return o;
}

void Resampler::set_cuda_graphs(bool on) {
  config_.cuda_graphs = on;
  if (!on) generator_->reverse_fn->clear_graphs();
}

torch::Tensor Resampler::decode_logits(const torch::Tensor& shape_latent) {
  torch::NoGradGuard no_grad;
  // Tokens -> grid as the official pipeline, then the decoder in chunks (autocast in the precision).
  const auto grid = models::shape_tokens_to_grid(shape_latent.to(device_, torch::kFloat32));  // [B, 8, k, k, k]
  std::vector<torch::Tensor> out;
  for (int64_t i = 0; i < grid.size(0); i += config_.decode_batch) {
    const auto chunk = grid.slice(0, i, std::min<int64_t>(i + config_.decode_batch, grid.size(0)));
    models::Autocast autocast(precision_, device_.is_cuda());
    out.push_back(decoder_->forward(chunk).to(torch::kFloat32));
  }
  return torch::cat(out, 0);  // [B, 1, R, R, R]
}

void mesh_from_logits(const torch::Tensor& logits_in, ResampledShape& out, double surface_offset) {
  auto logits = logits_in.detach().to(torch::kCPU, torch::kFloat32);
  if (logits.dim() == 3) logits = logits.unsqueeze(0).unsqueeze(0);
  SIMU_CHECK(logits.dim() == 5 && logits.size(0) == 1 && logits.size(1) == 1,
             "mesh_from_logits: expected [R, R, R] or [1, 1, R, R, R], got {}", logits.sizes());
  const int64_t resolution = logits.size(2);
  // Occupied voxels (official threshold logit > 0) as (x, y, z) in row-major order, as
  // models::occupied_coords without the batch column: counted per x-slice in parallel, then filled.
  {
    const auto grid = logits[0][0].contiguous();  // [R, R, R]
    const float* g = grid.data_ptr<float>();
    const int64_t X = grid.size(0), Y = grid.size(1), Z = grid.size(2);
    std::vector<int64_t> offset(static_cast<size_t>(X) + 1, 0);
    at::parallel_for(0, X, 4, [&](int64_t b, int64_t e) {
      for (int64_t x = b; x < e; ++x) {
        int64_t n = 0;
        for (int64_t i = x * Y * Z; i < (x + 1) * Y * Z; ++i) n += g[i] > 0;
        offset[x + 1] = n;
      }
    });
    for (int64_t x = 0; x < X; ++x) offset[x + 1] += offset[x];
    out.coords = torch::empty({offset[X], 3}, torch::kInt32);
    int32_t* c = out.coords.data_ptr<int32_t>();
    at::parallel_for(0, X, 4, [&](int64_t b, int64_t e) {
      for (int64_t x = b; x < e; ++x) {
        int32_t* o = c + 3 * offset[x];
        for (int64_t y = 0; y < Y; ++y)
          for (int64_t z = 0; z < Z; ++z)
            if (g[(x * Y + y) * Z + z] > 0) {
              *o++ = static_cast<int32_t>(x);
              *o++ = static_cast<int32_t>(y);
              *o++ = static_cast<int32_t>(z);
            }
      }
    });
  }
  if (out.coords.size(0) == 0) {
    out.ok = false;
    out.message = kNoOccupiedVoxel;
    return;
  }
  // Surface at iso 0 in grid units -> official voxel frame -> canonical frame.
  out.mesh = marching_cubes(logits);
  // Moved inward by the learnt occupancy's outward bias (offset_surface), in grid units = voxels.
  offset_surface(out.mesh, surface_offset);
  grid_to_voxel_frame(out.mesh, resolution);
  out.canonical = canonicalize_mesh(out.mesh);
  out.ok = !out.mesh.empty();
  if (!out.ok) out.message = "marching cubes produced no triangles";
}

void decode_poses(const models::Latents& latents, const std::vector<const ResampleRequest*>& requests,
                  const std::vector<ResampledShape*>& outs, const std::string& convention) {
  models::Latents cpu_latents;
  for (const auto& [name, v] : latents) cpu_latents[name] = v.to(torch::kCPU, torch::kFloat32);
  for (size_t k = 0; k < outs.size(); ++k) {
    ResampledShape& out = *outs[k];
    const int64_t row = static_cast<int64_t>(k);
    for (const auto& [name, v] : cpu_latents) out.latents[name] = v.slice(0, row, row + 1).clone();
    // Pose (official convention, this object's scene scale and shift).
    models::PoseDecodeOptions po;
    po.convention = convention;
    po.scene_scale = requests[k]->scene_scale;
    po.scene_shift = requests[k]->scene_shift;
    const auto pose = models::decode_pose(out.latents, po);
    const auto R = pose.rotation[0].to(torch::kFloat64).contiguous();
    const auto T = pose.translation[0].to(torch::kFloat64).contiguous();
    const auto Sc = pose.scale[0].to(torch::kFloat64).contiguous();
    const auto Q = pose.quaternion[0].to(torch::kFloat64).contiguous();
    const double* rp = R.data_ptr<double>();
    for (int a = 0; a < 3; ++a) {
      for (int b = 0; b < 3; ++b) out.rotation(a, b) = rp[3 * a + b];
      out.translation(a) = T.data_ptr<double>()[a];
      out.scale(a) = Sc.data_ptr<double>()[a];
    }
    for (int a = 0; a < 4; ++a) out.quaternion(a) = Q.data_ptr<double>()[a];
  }
}

void mesh_rows(const torch::Tensor& logits, const std::vector<ResampledShape*>& outs, double surface_offset) {
  // With at least as many rows as threads the rows run in parallel (each single-threaded); otherwise
  // one row at a time, each marching cubes parallel inside. The meshes are the same either way.
  const int64_t n_rows = static_cast<int64_t>(outs.size());
  auto mesh_row = [&](int64_t k) {
    ResampledShape& out = *outs[static_cast<size_t>(k)];
    mesh_from_logits(logits.slice(0, k, k + 1), out, surface_offset);
    out.scale_canonical = out.scale / out.canonical.factor;
    out.translation_canonical = out.translation + out.rotation * out.scale.cwiseProduct(out.canonical.centre);
  };
  if (n_rows >= at::get_num_threads()) {
    at::parallel_for(0, n_rows, 1, [&](int64_t b, int64_t e) {
      for (int64_t k = b; k < e; ++k) mesh_row(k);
    });
  } else {
    for (int64_t k = 0; k < n_rows; ++k) mesh_row(k);
  }
}

std::vector<torch::Tensor> Resampler::conditions(const std::vector<ResampleRequest>& requests) {
  torch::NoGradGuard no_grad;
  std::vector<torch::Tensor> conds(requests.size());
  // Requests given as embedder inputs: stack each kwarg over them and embed in one forward.
  std::vector<size_t> to_embed;
  for (size_t i = 0; i < requests.size(); ++i) {
    if (requests[i].cond.defined()) {
      conds[i] = requests[i].cond;
    } else {
      SIMU_CHECK(!requests[i].inputs.empty(), "resampler: request {} has neither condition tokens nor embedder inputs", i);
      SIMU_CHECK(embedder_, "resampler: request {} gives embedder inputs but no embedder_config is set", i);
      to_embed.push_back(i);
    }
  }
  if (to_embed.empty()) return conds;
  std::map<std::string, torch::Tensor> batch;
  for (const auto& name : embedder_->input_names()) {
    std::vector<torch::Tensor> parts;
    for (size_t i : to_embed) {
      auto it = requests[i].inputs.find(name);
      SIMU_CHECK(it != requests[i].inputs.end(), "resampler: request {} lacks embedder input '{}'", i, name);
      const int64_t image_dims = 3;  // [ch, H, W] unbatched
      parts.push_back(it->second.dim() == image_dims ? it->second.unsqueeze(0) : it->second);
    }
    batch[name] = torch::cat(parts, 0).to(device_, torch::kFloat32);
  }
  models::Autocast autocast(precision_, device_.is_cuda());
  const auto tokens = embedder_->forward(batch).to(torch::kCPU, torch::kFloat32);  // [n, L, C]
  for (size_t k = 0; k < to_embed.size(); ++k) conds[to_embed[k]] = tokens[static_cast<int64_t>(k)];
  return conds;
}

uint64_t retry_noise_seed(uint64_t seed, int attempt) {
  if (attempt <= 0) return seed;
  // splitmix64(x) is one step of the SplitMix64 generator from state x: its k-th output from state
  // `seed` is splitmix64(seed + (k - 1) * golden gamma).
  return splitmix64(seed + static_cast<uint64_t>(attempt - 1) * 0x9E3779B97F4A7C15ULL);
}

bool empty_occupancy(const ResampledShape& shape) {
  return !shape.ok && shape.coords.defined() && shape.coords.size(0) == 0;
}

void sample_with_retries(const std::vector<ResampledShape*>& outs, uint64_t seed, int max_retries,
                         const SampleAttempt& attempt) {
  std::vector<size_t> rows(outs.size());
  for (size_t k = 0; k < rows.size(); ++k) rows[k] = k;
  attempt(rows, seed);
  for (int retry = 1; retry <= max_retries; ++retry) {
    rows.clear();
    for (size_t k = 0; k < outs.size(); ++k)
      if (empty_occupancy(*outs[k])) rows.push_back(k);
    if (rows.empty()) break;
    for (size_t k : rows) *outs[k] = ResampledShape{};
    attempt(rows, retry_noise_seed(seed, retry));
    for (size_t k : rows) outs[k]->retries = retry;
  }
  const auto times = [](int n) { return fmt::format("{} time{}", n, n == 1 ? "" : "s"); };
  for (ResampledShape* out : outs) {
    if (out->retries == 0) continue;
    const std::string empties = out->retries == 1 ? "an empty decode" : fmt::format("{} empty decodes", out->retries);
    if (out->ok)
      out->message = fmt::format("retried {} with fresh noise after {} (every logit <= 0)", times(out->retries), empties);
    else if (empty_occupancy(*out))
      out->message = fmt::format("{} in {} attempts (retried {} with fresh noise)", kNoOccupiedVoxel,
                                 out->retries + 1, times(out->retries));
    else
      out->message = fmt::format("{} (retried {} with fresh noise after {})", out->message, times(out->retries), empties);
  }
}

ResampleResult Resampler::resample(const std::vector<ResampleRequest>& requests, uint64_t seed, int samples) {
  torch::NoGradGuard no_grad;
  ResampleResult result;
  SIMU_CHECK(samples >= 0, "resampler: samples {} must be >= 0 (0: num_samples)", samples);
  const int64_t S = samples > 0 ? samples : config_.num_samples;
  const int64_t n = static_cast<int64_t>(requests.size());
  result.objects.assign(requests.size(), std::vector<ResampledShape>(static_cast<size_t>(S)));
  if (n == 0) return result;
  const auto& mc = generator_->config().backbone;
  // Condition tokens (embedding where needed); check them.
  auto t_embed = std::chrono::steady_clock::now();
  const auto conds_all = conditions(requests);
  result.seconds_embed = seconds_since(t_embed);
  for (int64_t i = 0; i < n; ++i) {
    const auto& c = conds_all[i];
    SIMU_CHECK(c.defined() && c.dim() == 2 && c.size(1) == mc.cond_channels,
               "resampler: request {} condition must be [L, {}], got {}", i, mc.cond_channels,
               c.defined() ? fmt::format("{}", c.sizes()) : std::string("nothing"));
  }
  // Row k = r * S + s is request r's sample s.
  std::vector<ResampledShape*> outs;
  for (auto& samples : result.objects)
    for (auto& shape : samples) outs.push_back(&shape);
  const auto options = sample_options();

  // One attempt on some rows: noise for every (request, sample) row, in request order, from one CPU
  // generator seeded with noise_seed; the given rows grouped by condition length (one batched sampling
  // per length), decoded, posed and meshed.
  auto attempt = [&](const std::vector<size_t>& rows_in, uint64_t noise_seed) {
    auto rng = at::make_generator<at::CPUGeneratorImpl>(noise_seed);
    const models::Latents noise = generator_->noise(n * S, rng, torch::kCPU);
    std::map<int64_t, std::vector<int64_t>> groups;  // condition length -> rows (ascending)
    for (size_t k : rows_in) groups[conds_all[static_cast<int64_t>(k) / S].size(0)].push_back(static_cast<int64_t>(k));
    for (const auto& [L, rows] : groups) {
      const auto row_index = torch::tensor(rows, torch::kLong);
      std::vector<torch::Tensor> conds;
      for (int64_t k : rows) conds.push_back(conds_all[static_cast<size_t>(k / S)].to(torch::kFloat32).unsqueeze(0));
      const auto cond = torch::cat(conds, 0).to(device_);  // [rows, L, C]
      models::Latents x0;
      for (const auto& [name, v] : noise) x0[name] = v.index_select(0, row_index).to(device_);

      // One batched Stage-1 sampling for every row of the group.
      auto t0 = std::chrono::steady_clock::now();
      const models::Latents latents = generator_->sample(cond, x0, options);
      sync(device_);
      result.seconds_sample += seconds_since(t0);
      ++result.sampling_calls;

      // Shape -> occupancy logits (batched decoder).
      t0 = std::chrono::steady_clock::now();
      const auto logits = decode_logits(latents.at("shape")).to(torch::kCPU);  // [rows, 1, R, R, R]
      result.seconds_decode += seconds_since(t0);

      // Per row: latents and pose, then mesh.
      t0 = std::chrono::steady_clock::now();
      std::vector<ResampledShape*> group_outs;
      std::vector<const ResampleRequest*> reqs;
      for (int64_t k : rows) {
        group_outs.push_back(outs[static_cast<size_t>(k)]);
        reqs.push_back(&requests[static_cast<size_t>(k / S)]);
      }
      decode_poses(latents, reqs, group_outs, config_.pose_convention);
      mesh_rows(logits, group_outs, config_.surface_offset);
      result.seconds_mesh += seconds_since(t0);
    }
  };
  sample_with_retries(outs, seed, config_.empty_retries, attempt);
  for (size_t k = 0; k < outs.size(); ++k) {
    const ResampledShape& out = *outs[k];
    if (!out.ok || out.retries > 0)
      simu::log::warn("resampler: request {} sample {}: {}", k / static_cast<size_t>(S), k % static_cast<size_t>(S),
                      out.message);
  }
  return result;
}

}  // namespace simu::resample
