// The model a program runs when it is given no weights: the shipped miniature (weights/miniature_cpu,
// docs/miniature.md), a small SAM 3D Stage-1 model trained from scratch on the procedural shape world.
// It is not SAM 3D: programs say so when they use it. --random-weights keeps the random initialisation.
#pragma once

#include <string>

#include "data/preprocess.h"

namespace simu::resample {

struct ResamplerConfig;

// The shipped model's folder: $SIMU_DEFAULT_MODEL when set, else <source>/weights/miniature_cpu.
std::string shipped_model_dir();

// The files of a model folder, from its manifest.json ("files": paths relative to the folder).
struct ModelFolder {
  std::string dir, name, description;
  std::string generator_config, generator_weights, embedder_config, embedder_weights, decoder_config,
      decoder_weights, preprocess;
  std::string resample_adapter;  // optional (files.resample_adapter): the FM-DPO adapter folder for resampling
  // Optional (files.encoder_config / encoder_weights, together): the sparse-structure encoder whose
  // latents the model was trained on (build_pairs --preferred gt-latent).
  std::string encoder_config, encoder_weights;
  // Optional (mesh.surface_offset_voxels, default 0): ResamplerConfig::surface_offset for this model.
  double surface_offset = 0.0;
  // Reads dir/manifest.json; every file must exist (simu::Error naming the manifest and the key).
  static ModelFolder load(const std::string& dir);
};

// When c names no weight file at all, is not a random-weights run, and keeps the default configs
// (nothing to contradict): fills c with the shipped model (configs, weights, preprocessing) and returns
// a one-line note for logs and reports ("" when c is left as it was). With c.shipped_resample_adapter,
// no c.adapter_dir and a folder that has one, its resampling adapter too (adapter_resample_only). A
// missing shipped folder leaves c as it was (the usual missing-weights error follows).
std::string apply_shipped_model(ResamplerConfig& c);

// The preprocessing a choice names: "" or "model" = the model's (c.preprocess; the released preset when
// that is empty), else a preset name (released, default) or a YAML file of data::PreprocessConfig keys.
data::PreprocessConfig preprocess_choice(const std::string& choice, const ResamplerConfig& c);

}  // namespace simu::resample
