// sample_stage1: Stage-1 sampling. Loads the generator (config + safetensors weights) and condition
// tokens, draws the initial noise from --seed, integrates the flow with CFG and writes the sampled
// latents (shape [B, 4096, 8] and the pose latents) to a safetensors file.
#include <fmt/ranges.h>

#include <ATen/CPUGeneratorImpl.h>

#include <algorithm>

#include "common/cli.h"
#include "common/error.h"
#include "common/log.h"
#include "data/safetensors.h"
#include "models/generator.h"

namespace {

// Condition tokens [B, L, C] from a safetensors file: the named key, or the only tensor in the file.
torch::Tensor read_condition(const std::string& path, const std::string& key) {
  const auto f = simu::data::SafeTensorsFile::open(path);
  std::string k = key;
  if (k.empty()) {
    SIMU_CHECK(f.keys().size() == 1, "{}: holds {} tensors ({}); name the condition with --cond-key", path,
               f.keys().size(), fmt::join(f.keys(), ", "));
    k = f.keys().front();
  }
  SIMU_CHECK(f.contains(k), "{}: no tensor '{}' (has: {})", path, k, fmt::join(f.keys(), ", "));
  auto c = f.get(k).to(torch::kFloat32).clone();
  if (c.dim() == 2) c = c.unsqueeze(0);  // [L, C] -> [1, L, C]
  SIMU_CHECK(c.dim() == 3, "{}: tensor '{}' must be [B, L, C] or [L, C], got {} dims", path, k, c.dim());
  return c;
}

// --step-cache K (0 = off) and its settings (models/step_cache.h).
void add_step_cache_options(CLI::App& app, int& interval, simu::models::StepCacheOptions& o) {
  app.add_option("--step-cache", interval,
                 "opt-in step caching (docs/step_cache.md): a full model evaluation at least every K steps, "
                 "the shape velocity extrapolated and the pose velocity momentum-anchored in between; faster, at a "
                 "measured cost in fidelity. 0 = off (full sampling)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  app.add_option("--step-cache-order", o.order, "step caching: shape extrapolation order 0 | 1 | 2")->capture_default_str();
  app.add_option("--step-cache-momentum", o.pose_momentum, "step caching: pose momentum in [0, 1]")->capture_default_str();
  app.add_option("--step-cache-tolerance", o.tolerance,
                 "step caching: one more full step after a prediction error above this (0 = off)")
      ->capture_default_str();
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Sample SAM 3D Objects Stage-1 latents (shape + pose) from condition tokens. Sampler values default "
               "to the official inference pipeline's (25 steps, rescale_t 3, CFG 7 on t*1000 in [0, 500], add_flag, "
               "d = 0), not the training-time values of a released ss_generator.yaml; the values used are logged"};
  std::string config, weights, cond_path, cond_key, out = "stage1_latents.safetensors", device = "cuda", solver,
      sampler = "official", precision = "auto";
  int steps = 0;
  double cfg_strength = -1, rescale_t = 0;
  std::vector<double> cfg_interval;
  int64_t seed = 0, samples = 1;
  bool shortcut = false, fp32 = false;
  int step_cache = 0;
  simu::models::StepCacheOptions cache;
  app.add_option("--config", config, "generator config: official ss_generator.yaml/json or project yaml")->required();
  app.add_option("--weights", weights, "generator weights (.safetensors; convert .ckpt with scripts/convert_checkpoint.py)")
      ->required();
  app.add_option("--cond", cond_path, "safetensors file with condition tokens [B, L, C] or [L, C]")->required();
  app.add_option("--cond-key", cond_key, "tensor name in --cond (default: the only tensor)");
  app.add_option("--sampler", sampler,
                 "where unset sampler values come from: official (the official inference pipeline's) or config "
                 "(the generator config's inference_steps/rescale_t/strength/interval/no_shortcut)")
      ->capture_default_str()
      ->check(CLI::IsMember({"official", "config"}));
  auto* o_steps = app.add_option("--steps", steps, "solver steps (default: 25, or the config's with --sampler config)");
  auto* o_cfg = app.add_option("--cfg-strength", cfg_strength, "CFG strength (default: 7, or the config's)");
  auto* o_resc = app.add_option("--rescale-t", rescale_t, "time-grid rescale (default: 3, or the config's)");
  auto* o_int = app.add_option("--cfg-interval", cfg_interval, "CFG interval lo hi in t*time_scale (default: 0 500)")
                    ->expected(2);
  app.add_option("--seed", seed, "noise seed")->capture_default_str();
  app.add_option("--samples", samples, "samples per condition (the condition is repeated)")->capture_default_str();
  auto* o_solver = app.add_option("--solver", solver, "euler | midpoint | rk4 (default: the config's)");
  auto* o_short = app.add_flag("--shortcut", shortcut,
               "shortcut (distillation) mode: d = 1/steps and, unless --cfg-strength is given, no CFG "
               "(official sample_sparse_structure(use_distillation=True))");
  app.add_option("--precision", precision,
                 "fp16 | bf16 | fp32 | auto (fp16 on CUDA as the released pipeline, fp32 on CPU)")
      ->capture_default_str();
  app.add_flag("--fp32", fp32, "same as --precision fp32");
  add_step_cache_options(app, step_cache, cache);
  app.add_option("--device", device, "cpu | cuda | cuda:N")->capture_default_str();
  app.add_option("--out", out, "output safetensors file (latent.<name> tensors)")->capture_default_str();
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    const torch::Device dev(device);
    SIMU_CHECK(!dev.is_cuda() || torch::cuda::is_available(), "--device {}: no CUDA device here (use --device cpu)", device);
    auto gen = simu::models::load_generator(config, weights, dev, common.sets);
    auto cond = read_condition(cond_path, cond_key);
    SIMU_CHECK(cond.size(2) == gen->config().backbone.cond_channels, "{}: condition has {} channels, the model expects {}",
               cond_path, cond.size(2), gen->config().backbone.cond_channels);
    if (samples > 1) cond = cond.repeat_interleave(samples, 0);
    cond = cond.to(dev);

    // Sampling options: official inference values (or the config's), then what the command line sets.
    simu::models::SamplerOverrides user;
    if (o_steps->count()) user.steps = steps;
    if (o_cfg->count()) user.cfg_strength = cfg_strength;
    if (o_resc->count()) user.rescale_t = rescale_t;
    if (o_int->count()) user.cfg_interval = std::pair<double, double>{cfg_interval.at(0), cfg_interval.at(1)};
    if (o_solver->count()) user.solver = solver;
    if (o_short->count()) user.shortcut = shortcut;
    simu::models::SampleOptions o;
    if (sampler == "official") {
      o = simu::models::official_inference_options(gen->config(), user);
    } else {
      o = simu::models::SampleOptions::from(gen->config());
      if (user.steps) o.steps = *user.steps;
      if (user.shortcut && *user.shortcut) o.cfg_strength = 0, o.shortcut = true;
      if (user.cfg_strength) o.cfg_strength = *user.cfg_strength;
      if (user.rescale_t) o.rescale_t = *user.rescale_t;
      if (user.cfg_interval) o.cfg_interval = *user.cfg_interval;
      if (user.solver) o.solver = *user.solver;
    }
    const auto prec = simu::models::parse_precision(fp32 ? "fp32" : precision, dev, "--precision");
    simu::models::check_precision(prec, dev, "--precision");
    o.precision = prec;
    o.on_step = [](int i, int n) { simu::log::info("step {}/{}", i, n); };
    cache.enabled = step_cache > 0;
    cache.interval = std::max(step_cache, 1);
    cache.validate("--step-cache options: ");
    o.step_cache = cache;
    simu::log::info("sampler ({}): {}; step caching {}", sampler, simu::models::describe_sampler(o, gen->config(), user),
                    cache.describe());

    // Noise from a CPU generator (same seed -> same noise on every device).
    auto rng = at::make_generator<at::CPUGeneratorImpl>(static_cast<uint64_t>(seed));
    auto x0 = gen->noise(cond.size(0), rng, dev);
    simu::log::info("sampling {} x {} condition tokens", cond.size(0), cond.size(1));
    auto latents = gen->sample(cond, x0, o);
    if (cache.enabled)
      simu::log::info("step caching: {} of {} steps evaluated in full", gen->step_cache_stats().full_steps(), o.steps);

    // Write the latents (decoders read `latent.shape` and the pose latents from this file).
    std::map<std::string, torch::Tensor> tensors;
    for (const auto& [k, v] : latents) tensors["latent." + k] = v;
    simu::data::save_safetensors(out, tensors,
                                 {{"seed", std::to_string(seed)}, {"steps", std::to_string(o.steps)},
                                  {"cfg_strength", fmt::format("{}", o.cfg_strength)},
                                  {"rescale_t", fmt::format("{}", o.rescale_t)},
                                  {"cfg_interval", fmt::format("{} {}", o.cfg_interval.first, o.cfg_interval.second)},
                                  {"sampler", simu::models::describe_sampler(o, gen->config(), user)},
                                  {"config", config}, {"weights", weights}, {"solver", o.solver},
                                  {"shortcut", o.shortcut ? "1" : "0"}, {"step_cache", cache.describe()}});
    simu::log::info("wrote {} ({} latents)", out, latents.size());
    return 0;
  });
}
