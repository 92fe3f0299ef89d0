// The typed config of a Stage-1 pretraining run (train_stage1; configs/miniature/train_stage1.yaml):
// the sections every training run shares (TrainerConfig: optim, data, train, run, dist) plus the
// model, the shape-latent targets, the flow-matching objective, EMA, the export and the dataset split.
// Strict keys; every error names the file and the key.
#pragma once

#include <map>
#include <string>
#include <vector>

#include "common/config.h"
#include "training/train_config.h"

namespace simu::training {

// model: what is trained (from scratch unless init is given).
struct Stage1ModelConfig {
  std::string generator;  // generator config (project layout, or the official JSON/YAML)
  std::string embedder;   // condition embedder config (fixture JSON layout, or the official YAML)
  // Starting weights (a train_stage1 export or the released layout: _base_models.generator.* and
  // _base_models.condition_embedder.*); "" = the official initialisation (stage1_model.h).
  std::string init;
  static Stage1ModelConfig from(simu::config::Reader& r);
};

// targets: how a sample's shape-latent target is made from its occupancy.
struct TargetsConfig {
  // "encoder": the posterior mean of a trained, frozen sparse-structure encoder (encoder_config,
  // encoder_weights); "random_linear": a fixed random linear map of the occupancy, seeded by `seed`
  // (tests and smoke runs: it is no shape model).
  std::string kind = "encoder";
  std::string encoder_config, encoder_weights;
  uint64_t seed = 0;
  static TargetsConfig from(simu::config::Reader& r);
};

// objective: the flow-matching loss (the released FlowMatching / ShortCut recipe).
struct FlowObjectiveConfig {
  double t_mean = 0.0, t_std = 1.0;  // logit-normal t (official lognorm_sampler)
  // Condition dropout for classifier-free guidance (official ClassifierFreeGuidance p_unconditional):
  // a dropped sample's condition tokens are multiplied by 0 (the model's force_zeros_cond / add_flag
  // handling; "zeros" handling also zeroes d).
  double p_unconditional = 0.1;
  // Shortcut self-consistency targets (official ShortCut): this share of samples gets d from
  // {1/2^i, i < 8}, the model is asked for step 2d and trained towards the mean of two d-steps of
  // itself (no gradient); 0 (default) = plain flow matching (every d = 0). Needs a shortcut model.
  double shortcut_fraction = 0.0;
  double shortcut_weight = 1.0;        // official shortcut_loss_weight
  double shortcut_cfg_strength = 3.0;  // official self_consistency_cfg_strength (shape latent only)
  double shortcut_cfg_ratio = 0.5;     // official ratio_cfg_samples_in_self_consistency_target
  // Per-latent loss weights (official loss_weights); latents not named weigh 1.
  std::map<std::string, double> latent_weights;
  static FlowObjectiveConfig from(simu::config::Reader& r);
  double weight_of(const std::string& latent) const;
};

// ema: an exponential moving average of every trained parameter, updated after each step with
// decay min(decay, (1 + s) / (10 + s)) at step s (the usual warm-up).
struct EmaConfig {
  double decay = 0.999;
  static EmaConfig from(simu::config::Reader& r);
};

// export: the weights written to <out_dir>/model/ss_generator.safetensors at the end.
struct ExportConfig {
  std::string weights = "ema";   // "ema" or "raw"
  std::string dtype = "float32";  // "float32" or "float16"
  static ExportConfig from(simu::config::Reader& r);
};

// dataset: which records of the cache are trained on.
struct DatasetConfig {
  std::string split = "train";
  static DatasetConfig from(simu::config::Reader& r);
};

struct Stage1Config : TrainerConfig {
  Stage1ModelConfig model;
  TargetsConfig targets;
  FlowObjectiveConfig objective;
  EmaConfig ema;
  ExportConfig export_;
  DatasetConfig dataset;
  // Loads a file with "a.b=v" overrides; unknown keys or bad values are errors naming file and key.
  static Stage1Config load(const std::string& path, const std::vector<std::string>& overrides = {});
  static Stage1Config from(simu::config::Reader& r);
};

}  // namespace simu::training
