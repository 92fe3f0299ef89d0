#include "common/source_dir.h"
#include "pipeline/resample/model_options.h"

#include "pipeline/resample/default_model.h"
#include "pipeline/resample/lift.h"

#include <algorithm>

namespace simu::resample {

ModelOptions::ModelOptions() {
  config.embedder_config = simu::source_dir() + "/configs/cond_embedder_sam3d_stage1.yaml";
}

void add_model_options(CLI::App& app, ModelOptions& o, const ModelOptionFlags& flags, const std::string& group) {
  ResamplerConfig& c = o.config;
  // Models and weights.
  app.add_option("--generator-config", c.generator_config, "Stage-1 generator config")->capture_default_str()->group(group);
  app.add_option("--generator-weights", c.generator_weights, "generator safetensors (converted ss_generator.ckpt)")
      ->group(group);
  app.add_option("--decoder-config", c.decoder_config, "sparse-structure decoder config")->capture_default_str()->group(group);
  app.add_option("--decoder-weights", c.decoder_weights, "decoder safetensors (converted ss_decoder.ckpt)")->group(group);
  app.add_option("--embedder-config", c.embedder_config, "condition embedder config")->capture_default_str()->group(group);
  app.add_option("--embedder-weights", c.embedder_weights,
                 "condition embedder safetensors (the converted ss_generator.safetensors holds it)")
      ->group(group);
  app.add_option("--preprocess", o.preprocess,
                 "condition preprocessing: released | default | FILE.yaml (data::PreprocessConfig keys); empty = the "
                 "model's (the shipped miniature's own sizes, else released)")
      ->group(group);
  if (flags.adapter) app.add_option("--adapter", c.adapter_dir, "PEFT LoRA adapter directory (optional)")->group(group);
  app.add_flag("--random-weights", o.random_weights, "allow missing weight files: random init (smoke runs, benchmarks)")
      ->group(group);
  // Where and how it runs.
  app.add_option("--device", c.device, "auto | cpu | cuda | cuda:N")->capture_default_str()->group(group);
  app.add_option("--precision", o.precision, "auto | fp16 | bf16 | fp32 (auto: fp16 autocast on CUDA as released, fp32 on CPU)")
      ->capture_default_str()
      ->group(group);
  app.add_option("--steps", c.steps, "Stage-1 sampling steps (released inference: 25)")->capture_default_str()->group(group);
  app.add_option("--cfg-strength", c.cfg_strength,
                 "classifier-free guidance strength of the Stage-1 sampling (released inference: 7; a model config's "
                 "own value is not used)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber)
      ->group(group);
  app.add_option("--surface-offset", c.surface_offset,
                 "voxels the meshes' surface is moved inward after marching cubes (the learnt occupancy sits outside "
                 "the object; docs/lift.md). Default: the model's (the shipped miniature's manifest, else 0)")
      ->check(CLI::Range(0.0, 2.0))
      ->group(group);
  if (flags.samples)
    app.add_option("--samples", c.num_samples, "shapes drawn per object")
        ->capture_default_str()
        ->check(CLI::PositiveNumber)
        ->group(group);
  if (flags.seed) app.add_option("--seed", o.seed, "sampling seed")->capture_default_str()->group(group);
  // Opt-in step caching of the Stage-1 sampling (models/step_cache.h).
  auto& sc = c.step_cache;
  app.add_option("--step-cache", o.step_cache_interval,
                 "opt-in step caching: a full Stage-1 evaluation at least every K steps, the shape velocity extrapolated "
                 "and the pose velocity momentum-anchored in between (faster, at a measured cost in fidelity; "
                 "docs/step_cache.md). 0 = off")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber)
      ->group(group);
  app.add_option("--step-cache-order", sc.order, "step caching: shape extrapolation order 0 | 1 | 2")
      ->capture_default_str()
      ->group(group);
  app.add_option("--step-cache-momentum", sc.pose_momentum, "step caching: pose momentum in [0, 1]")
      ->capture_default_str()
      ->group(group);
}

std::string finish_model_options(ModelOptions& o) {
  // No weights at all: the shipped miniature (default_model.h), unless --random-weights.
  o.config.random_weights = o.random_weights;
  o.shipped_note = apply_shipped_model(o.config);
  if (!o.preprocess.empty()) o.config.preprocess = o.preprocess;
  (void)preprocess_choice("model", o.config);  // a bad --preprocess fails here, before the models load
  const std::string banner = check_lift_weights(o.config, o.random_weights);
  apply_precision(o.config, o.precision);
  o.config.step_cache.enabled = o.step_cache_interval > 0;
  o.config.step_cache.interval = std::max(o.step_cache_interval, 1);
  o.config.step_cache.validate("--step-cache options: ");
  o.config.random_weights = o.random_weights;
  return banner;
}

}  // namespace simu::resample
