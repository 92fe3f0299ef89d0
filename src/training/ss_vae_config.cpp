#include "training/ss_vae_config.h"

#include <cmath>

#include "common/config_check.h"
#include "common/error.h"

namespace simu::training {

namespace {

using simu::config::check_in;
using simu::config::choice_field;
using simu::config::int_field;

// The section `name` of r, read with T::from.
template <class T>
T section(simu::config::Reader& r, const char* name) {
  auto s = r.child(name);
  return T::from(s);
}

// A non-negative finite weight of `key` (when present).
void weight_field(simu::config::Reader& r, const char* key, double& value) {
  r.field(key, value);
  check_in(r, key, value, 0.0, 1e6, false, "[0, 1e6]");
}

}  // namespace

SsVaeModelConfig SsVaeModelConfig::from(simu::config::Reader& r) {
  SsVaeModelConfig c;
  SIMU_CHECK(r.has("encoder") && r.has("decoder"), "{}: section '{}' needs both 'encoder' and 'decoder'", r.file(),
             r.full("model"));
  auto enc = r.child("encoder");
  c.encoder = models::SSEncoderConfig::from(enc);
  auto dec = r.child("decoder");
  c.decoder = models::SSDecoderConfig::from(dec);
  choice_field(r, "export_dtype", c.export_dtype, {"float32", "float16"});
  r.field("frozen_encoder", c.frozen_encoder);
  return c;
}

SsVaeLossConfig SsVaeLossConfig::from(simu::config::Reader& r) {
  SsVaeLossConfig c;
  weight_field(r, "bce", c.bce);
  weight_field(r, "dice", c.dice);
  weight_field(r, "l1", c.l1);
  weight_field(r, "lambda_kl", c.lambda_kl);
  SIMU_CHECK(c.bce + c.dice + c.l1 > 0, "{}: section 'loss' needs a positive weight on bce, dice or l1", r.file());
  return c;
}

SsVaeDataConfig SsVaeDataConfig::from(simu::config::Reader& r) {
  SsVaeDataConfig c;
  int_field(r, "resolution", c.resolution, 2, 512);
  int_field(r, "encoder_resolution", c.encoder_resolution, 0, 512);
  int_field(r, "global_batch", c.global_batch, 1);
  int_field(r, "train_instances", c.train_instances, 0);
  r.field("families", c.families);
  int_field(r, "workers", c.workers, 1, 256);
  int_field(r, "prefetch", c.prefetch, 1, 1024);
  r.field("seed", c.seed);
  return c;
}

SsVaeLoopConfig SsVaeLoopConfig::from(simu::config::Reader& r) {
  SsVaeLoopConfig c;
  int_field(r, "steps", c.steps, 1);
  choice_field(r, "precision", c.precision, {"bf16", "fp32"});
  r.field("seed", c.seed);
  choice_field(r, "device", c.device, {"cuda", "cpu"});
  r.field("ema_rate", c.ema_rate);
  r.field("cudnn_benchmark", c.cudnn_benchmark);
  check_in(r, "ema_rate", c.ema_rate, 0.0, 1.0, false, "[0, 1)");
  SIMU_CHECK(c.ema_rate < 1.0, "{}: key '{}': expected a rate in [0, 1) (0 = no EMA), got 1", r.file(), r.full("ema_rate"));
  return c;
}

SsVaeEvalConfig SsVaeEvalConfig::from(simu::config::Reader& r) {
  SsVaeEvalConfig c;
  int_field(r, "every", c.every, 0);
  int_field(r, "val_per_family", c.val_per_family, 0);
  int_field(r, "test_per_family", c.test_per_family, 0);
  int_field(r, "batch", c.batch, 1);
  return c;
}

SsVaeConfig SsVaeConfig::from(simu::config::Reader& r) {
  SsVaeConfig c;
  c.model = section<SsVaeModelConfig>(r, "model");
  c.loss = section<SsVaeLossConfig>(r, "loss");
  c.optim = section<OptimConfig>(r, "optim");
  c.data = section<SsVaeDataConfig>(r, "data");
  c.train = section<SsVaeLoopConfig>(r, "train");
  c.eval = section<SsVaeEvalConfig>(r, "eval");
  c.run = section<RunConfig>(r, "run");
  c.dist = section<DistConfig>(r, "dist");
  r.finish();
  c.file = r.file();
  c.resolved = YAML::Clone(r.node());
  // The sections must fit together: one occupancy channel in and out, one latent, one grid.
  const auto& enc = c.model.encoder;
  const auto& dec = c.model.decoder;
  SIMU_CHECK(enc.in_channels == 1 && dec.out_channels == 1,
             "{}: the VAE reconstructs one occupancy channel: model.encoder.in_channels and model.decoder.out_channels "
             "must be 1 (got {} and {})",
             c.file, enc.in_channels, dec.out_channels);
  SIMU_CHECK(enc.latent_channels == dec.latent_channels,
             "{}: model.encoder.latent_channels {} differs from model.decoder.latent_channels {}", c.file,
             enc.latent_channels, dec.latent_channels);
  const int64_t er = c.encoder_resolution();
  SIMU_CHECK(er % enc.downsample_factor() == 0,
             "{}: the encoder's input side {} (data.encoder_resolution, or data.resolution when 0) is not divisible by "
             "its down-sampling factor {} ({} levels)",
             c.file, er, enc.downsample_factor(), enc.channels.size());
  SIMU_CHECK(c.latent_resolution() * dec.upsample_factor() == c.data.resolution,
             "{}: the encoder maps {}^3 (data.encoder_resolution, or data.resolution when 0) to a {}^3 latent "
             "(down-sampling {}, {} levels), which the decoder (up-sampling "
             "{}, {} levels) decodes to {}^3, but data.resolution is {}",
             c.file, er, c.latent_resolution(), enc.downsample_factor(), enc.channels.size(), dec.upsample_factor(),
             dec.channels.size(), c.latent_resolution() * dec.upsample_factor(), c.data.resolution);
  SIMU_CHECK(!dec.reshape_input_to_cube, "{}: model.decoder.reshape_input_to_cube must be false: the VAE decodes the "
             "encoder's [B, C, r, r, r] latent", c.file);
  SIMU_CHECK(!enc.use_fp16 && !dec.use_fp16,
             "{}: use_fp16 keeps the torso's parameters in float16, which AdamW cannot train: set "
             "train.precision bf16 for mixed precision instead",
             c.file);
  return c;
}

SsVaeConfig SsVaeConfig::load(const std::string& path, const std::vector<std::string>& overrides) {
  simu::config::Reader r(simu::config::load_file(path, overrides), path);
  return from(r);
}

const std::vector<std::string>& ss_vae_run_outputs() {
  static const std::vector<std::string> names = {"checkpoints", "metrics.jsonl", "tensorboard", "weights", "eval.json"};
  return names;
}

}  // namespace simu::training
