#include "training/stage1_config.h"

#include <cmath>

#include <fmt/ranges.h>

#include "common/config_check.h"
#include "common/error.h"
#include "data/stage1_cache.h"

namespace simu::training {

namespace {

template <class T>
T section(simu::config::Reader& r, const char* name) {
  auto s = r.child(name);
  return T::from(s);
}

}  // namespace

Stage1ModelConfig Stage1ModelConfig::from(simu::config::Reader& r) {
  Stage1ModelConfig c;
  c.generator = r.require<std::string>("generator");
  c.embedder = r.require<std::string>("embedder");
  r.field("init", c.init);
  return c;
}

TargetsConfig TargetsConfig::from(simu::config::Reader& r) {
  TargetsConfig c;
  simu::config::choice_field(r, "kind", c.kind, {"encoder", "random_linear"});
  r.field("encoder_config", c.encoder_config);
  r.field("encoder_weights", c.encoder_weights);
  r.field("seed", c.seed);
  if (c.kind == "encoder" && (c.encoder_config.empty() || c.encoder_weights.empty()))
    fail_hint("train the sparse-structure VAE first (train_ss_vae) and give its encoder's config and weights",
              "{}: keys '{}' and '{}' are needed for targets.kind encoder (the frozen encoder makes the shape "
              "latents)", r.file(), r.full("encoder_config"), r.full("encoder_weights"));
  return c;
}

FlowObjectiveConfig FlowObjectiveConfig::from(simu::config::Reader& r) {
  FlowObjectiveConfig c;
  r.field("t_mean", c.t_mean);
  r.field("t_std", c.t_std);
  r.field("p_unconditional", c.p_unconditional);
  r.field("shortcut_fraction", c.shortcut_fraction);
  r.field("shortcut_weight", c.shortcut_weight);
  r.field("shortcut_cfg_strength", c.shortcut_cfg_strength);
  r.field("shortcut_cfg_ratio", c.shortcut_cfg_ratio);
  r.field("latent_weights", c.latent_weights);
  using simu::config::check_in;
  check_in(r, "t_mean", c.t_mean, -100, 100, false, "[-100, 100]");
  check_in(r, "t_std", c.t_std, 0, 100, true, "(0, 100]");
  check_in(r, "p_unconditional", c.p_unconditional, 0, 1, false, "[0, 1)");
  SIMU_CHECK(c.p_unconditional < 1, "{}: key '{}': expected a finite number in [0, 1), got {} (no sample would see its "
             "condition)", r.file(), r.full("p_unconditional"), c.p_unconditional);
  check_in(r, "shortcut_fraction", c.shortcut_fraction, 0, 1, false, "[0, 1)");
  SIMU_CHECK(c.shortcut_fraction < 1, "{}: key '{}': expected a number in [0, 1), got {} (no sample would learn the "
             "flow itself)", r.file(), r.full("shortcut_fraction"), c.shortcut_fraction);
  check_in(r, "shortcut_weight", c.shortcut_weight, 0, 1e6, false, "[0, 1e6]");
  check_in(r, "shortcut_cfg_strength", c.shortcut_cfg_strength, 0, 100, false, "[0, 100]");
  check_in(r, "shortcut_cfg_ratio", c.shortcut_cfg_ratio, 0, 1, false, "[0, 1]");
  for (const auto& [name, w] : c.latent_weights)
    SIMU_CHECK(std::isfinite(w) && w >= 0, "{}: key '{}.{}': expected a finite weight >= 0, got {}", r.file(),
               r.full("latent_weights"), name, w);
  return c;
}

double FlowObjectiveConfig::weight_of(const std::string& latent) const {
  const auto it = latent_weights.find(latent);
  return it == latent_weights.end() ? 1.0 : it->second;
}

EmaConfig EmaConfig::from(simu::config::Reader& r) {
  EmaConfig c;
  r.field("decay", c.decay);
  simu::config::check_in(r, "decay", c.decay, 0, 1, false, "[0, 1)");
  SIMU_CHECK(c.decay < 1, "{}: key '{}': expected a number in [0, 1), got {}", r.file(), r.full("decay"), c.decay);
  return c;
}

ExportConfig ExportConfig::from(simu::config::Reader& r) {
  ExportConfig c;
  simu::config::choice_field(r, "weights", c.weights, {"ema", "raw"});
  simu::config::choice_field(r, "dtype", c.dtype, {"float32", "float16"});
  return c;
}

DatasetConfig DatasetConfig::from(simu::config::Reader& r) {
  DatasetConfig c;
  r.field("split", c.split);
  (void)data::parse_sample_split(c.split, r.file() + ": key '" + r.full("split") + "'");
  return c;
}

Stage1Config Stage1Config::from(simu::config::Reader& r) {
  Stage1Config c;
  c.model = section<Stage1ModelConfig>(r, "model");
  c.targets = section<TargetsConfig>(r, "targets");
  c.objective = section<FlowObjectiveConfig>(r, "objective");
  c.ema = section<EmaConfig>(r, "ema");
  c.export_ = section<ExportConfig>(r, "export");
  c.dataset = section<DatasetConfig>(r, "dataset");
  // Options of FM-DPO's data stream that do not apply: the split is loaded into memory once.
  if (r.has("data") && r.node()["data"].IsMap() && r.node()["data"]["prefetch"])
    fail_hint("remove it: the training split is held in memory and gathered per step with the read-ahead",
              "{}: key 'data.prefetch' applies to the pair cache's stream (train_fmdpo), not to train_stage1", r.file());
  c.read_shared(r);
  r.finish();
  // FM-DPO's frozen-base options do not apply to a model trained whole.
  SIMU_CHECK(!c.train.fp8_base, "{}: key 'train.fp8_base': the FP8 frozen base is FM-DPO's (a frozen base with "
             "adapters); Stage-1 pretraining trains every weight: set it to false", c.file);
  return c;
}

Stage1Config Stage1Config::load(const std::string& path, const std::vector<std::string>& overrides) {
  auto node = simu::config::load_file(path, overrides);
  simu::config::Reader r(node, path);
  return from(r);
}

}  // namespace simu::training
