// sample_stage1: Stage-1 sampling. Loads the generator (config + safetensors weights) and condition
// tokens, draws the initial noise from --seed, integrates the flow with CFG and writes the sampled
// latents (shape [B, 4096, 8] and the pose latents) to a safetensors file.
#include <fmt/ranges.h>

#include <ATen/CPUGeneratorImpl.h>

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

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Sample SAM 3D Objects Stage-1 latents (shape + pose) from condition tokens"};
  std::string config, weights, cond_path, cond_key, out = "stage1_latents.safetensors", device = "cuda", solver;
  int steps = 0;
  double cfg_strength = -1;
  int64_t seed = 0, samples = 1;
  bool shortcut = false, fp32 = false;
  app.add_option("--config", config, "generator config: official ss_generator.yaml/json or project yaml")->required();
  app.add_option("--weights", weights, "generator weights (.safetensors; convert .ckpt with scripts/convert_checkpoint.py)")
      ->required();
  app.add_option("--cond", cond_path, "safetensors file with condition tokens [B, L, C] or [L, C]")->required();
  app.add_option("--cond-key", cond_key, "tensor name in --cond (default: the only tensor)");
  app.add_option("--steps", steps, "solver steps (default: the config's inference_steps)");
  app.add_option("--cfg-strength", cfg_strength, "CFG strength (default: the config's)");
  app.add_option("--seed", seed, "noise seed")->capture_default_str();
  app.add_option("--samples", samples, "samples per condition (the condition is repeated)")->capture_default_str();
  app.add_option("--solver", solver, "euler | midpoint | rk4 (default: the config's)");
  app.add_flag("--shortcut", shortcut,
               "shortcut (distillation) mode: d = 1/steps and, unless --cfg-strength is given, no CFG "
               "(official sample_sparse_structure(use_distillation=True))");
  app.add_flag("--fp32", fp32, "no bf16 autocast on CUDA");
  app.add_option("--device", device, "cpu | cuda | cuda:N")->capture_default_str();
  app.add_option("--out", out, "output safetensors file (latent.<name> tensors)")->capture_default_str();
  simu::cli::CommonOptions common;
  simu::cli::add_common_options(app, common);
  return simu::cli::run(app, argc, argv, [&] {
    simu::cli::apply_common_options(common);
    const torch::Device dev(device);
    SIMU_CHECK(!dev.is_cuda() || torch::cuda::is_available(), "--device {}: no CUDA device here (use --device cpu)", device);
    auto gen = simu::models::load_generator(config, weights, dev, common.sets);
    auto cond = read_condition(cond_path, cond_key);
    SIMU_CHECK(cond.size(2) == gen->config().backbone.cond_channels, "{}: condition has {} channels, the model expects {}",
               cond_path, cond.size(2), gen->config().backbone.cond_channels);
    if (samples > 1) cond = cond.repeat_interleave(samples, 0);
    cond = cond.to(dev);

    // Sampling options: config defaults, then the command line.
    auto o = simu::models::SampleOptions::from(gen->config());
    if (steps > 0) o.steps = steps;
    if (shortcut) o.cfg_strength = 0;
    if (cfg_strength >= 0) o.cfg_strength = cfg_strength;
    if (!solver.empty()) o.solver = solver;
    if (shortcut) o.shortcut = true;
    o.bf16_autocast = !fp32;
    o.on_step = [](int i, int n) { simu::log::info("step {}/{}", i, n); };

    // Noise from a CPU generator (same seed -> same noise on every device).
    auto rng = at::make_generator<at::CPUGeneratorImpl>(static_cast<uint64_t>(seed));
    auto x0 = gen->noise(cond.size(0), rng, dev);
    simu::log::info("sampling {} x {} condition tokens, {} steps, cfg {}, solver {}{}", cond.size(0), cond.size(1), o.steps,
                    o.cfg_strength, o.solver, o.shortcut ? ", shortcut" : "");
    auto latents = gen->sample(cond, x0, o);

    // Write the latents (decoders read `latent.shape` and the pose latents from this file).
    std::map<std::string, torch::Tensor> tensors;
    for (const auto& [k, v] : latents) tensors["latent." + k] = v;
    simu::data::save_safetensors(out, tensors,
                                 {{"seed", std::to_string(seed)}, {"steps", std::to_string(o.steps)},
                                  {"cfg_strength", fmt::format("{}", o.cfg_strength)}, {"config", config},
                                  {"weights", weights}, {"solver", o.solver}, {"shortcut", o.shortcut ? "1" : "0"}});
    simu::log::info("wrote {} ({} latents)", out, latents.size());
    return 0;
  });
}
