#include "pipeline/resample/default_model.h"

#include <cmath>
#include <cstdlib>
#include <filesystem>

#include "common/config.h"
#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "common/source_dir.h"
#include "common/text.h"
#include "pipeline/resample/resampler.h"

namespace simu::resample {

std::string shipped_model_dir() {
  if (const char* env = std::getenv("SIMU_DEFAULT_MODEL"); env && *env) return env;
  return simu::source_dir() + "/weights/miniature_cpu";
}

ModelFolder ModelFolder::load(const std::string& dir) {
  const std::string path = dir + "/manifest.json";
  const auto j = simu::text::parse_json(simu::fs::read_file(path), path);
  ModelFolder m;
  m.dir = dir;
  m.name = j.value("name", std::string("model"));
  m.description = j.value("description", std::string());
  SIMU_CHECK(j.contains("files") && j["files"].is_object(), "{}: no \"files\" object", path);
  const auto& f = j["files"];
  // Each file relative to the folder; every one must be there.
  auto file = [&](const char* key) {
    SIMU_CHECK(f.contains(key) && f[key].is_string(), "{}: files.{} missing or not a string", path, key);
    const std::string p = dir + "/" + f[key].get<std::string>();
    SIMU_CHECK(std::filesystem::exists(p), "{}: files.{}: {} not found", path, key, p);
    return p;
  };
  m.generator_config = file("generator_config");
  m.generator_weights = file("generator_weights");
  m.embedder_config = file("embedder_config");
  m.embedder_weights = file("embedder_weights");
  m.decoder_config = file("decoder_config");
  m.decoder_weights = file("decoder_weights");
  m.preprocess = file("preprocess");
  SIMU_CHECK(f.contains("encoder_config") == f.contains("encoder_weights"),
             "{}: files.encoder_config and files.encoder_weights come together", path);
  if (f.contains("encoder_config")) {
    m.encoder_config = file("encoder_config");
    m.encoder_weights = file("encoder_weights");
  }
  // Optional: the meshing's inward surface offset in voxels (ResamplerConfig::surface_offset).
  if (j.contains("mesh")) {
    SIMU_CHECK(j["mesh"].is_object() && j["mesh"].contains("surface_offset_voxels") && j["mesh"]["surface_offset_voxels"].is_number(),
               "{}: \"mesh\" must be an object with a number surface_offset_voxels", path);
    m.surface_offset = j["mesh"]["surface_offset_voxels"].get<double>();
    SIMU_CHECK(m.surface_offset >= 0 && m.surface_offset <= 2, "{}: mesh.surface_offset_voxels {} is outside [0, 2]", path,
               m.surface_offset);
  }
  if (f.contains("resample_adapter")) {
    m.resample_adapter = file("resample_adapter");
    SIMU_CHECK(std::filesystem::exists(m.resample_adapter + "/adapter_config.json"),
               "{}: files.resample_adapter: {} holds no adapter_config.json (a PEFT adapter folder)", path,
               m.resample_adapter);
  }
  return m;
}

std::string apply_shipped_model(ResamplerConfig& c) {
  if (c.random_weights || !c.generator_weights.empty() || !c.decoder_weights.empty() || !c.embedder_weights.empty())
    return "";
  // Only where nothing contradicts it: the configs are still the released defaults.
  const ResamplerConfig defaults;
  const std::string released_embedder = simu::source_dir() + "/configs/cond_embedder_sam3d_stage1.yaml";
  if (c.generator_config != defaults.generator_config || c.decoder_config != defaults.decoder_config ||
      (!c.embedder_config.empty() && c.embedder_config != released_embedder) || !c.generator_overrides.empty())
    return "";
  const std::string dir = shipped_model_dir();
  if (!std::filesystem::exists(dir + "/manifest.json")) return "";
  const ModelFolder m = ModelFolder::load(dir);
  c.generator_config = m.generator_config;
  c.generator_weights = m.generator_weights;
  c.embedder_config = m.embedder_config;
  c.embedder_weights = m.embedder_weights;
  c.decoder_config = m.decoder_config;
  c.decoder_weights = m.decoder_weights;
  if (c.preprocess.empty()) c.preprocess = m.preprocess;
  if (std::isnan(c.surface_offset)) c.surface_offset = m.surface_offset;
  std::string with_adapter;
  if (c.shipped_resample_adapter && c.adapter_dir.empty() && !m.resample_adapter.empty()) {
    c.adapter_dir = m.resample_adapter;
    c.adapter_resample_only = true;
    with_adapter = fmt::format(" Resampling uses its FM-DPO adapter ({}; the first lift the base model; "
                               "--base-resampling: the base model for both).",
                               m.resample_adapter);
  }
  const std::string note = fmt::format(
      "model: {} ({}): {}; not SAM 3D. Pass --generator-weights, --embedder-weights and --decoder-weights for "
      "the released model, or --random-weights.{}",
      m.name, dir, m.description, with_adapter);
  simu::log::info("{}", note);
  return note;
}

data::PreprocessConfig preprocess_choice(const std::string& choice, const ResamplerConfig& c) {
  const std::string& s = (choice.empty() || choice == "model") ? c.preprocess : choice;
  if (s.empty()) return data::PreprocessConfig::preset_named("released");
  if (s == "released" || s == "default") return data::PreprocessConfig::preset_named(s);
  SIMU_CHECK(std::filesystem::exists(s), "preprocessing '{}': not a preset (released, default) and no such file", s);
  config::Reader r(config::load_file(s), s);
  auto pre = data::PreprocessConfig::from(r);
  r.finish();
  return pre;
}

}  // namespace simu::resample
