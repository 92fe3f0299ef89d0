// The typed config of a sparse-structure VAE training run (train_ss_vae; configs/miniature/ss_vae.yaml):
// one struct per section, strict keys. The optim:, run: and dist: sections are the FM-DPO trainer's
// (training/optim.h, training/train_config.h).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <yaml-cpp/yaml.h>

#include "common/config.h"
#include "models/ss_decoder.h"
#include "models/ss_encoder.h"
#include "training/optim.h"
#include "training/train_config.h"

namespace simu::training {

// model: the two networks, in the layouts their loaders read (SSEncoderConfig / SSDecoderConfig::from),
// and the dtype of the exported weights.
struct SsVaeModelConfig {
  models::SSEncoderConfig encoder;
  models::SSDecoderConfig decoder;
  std::string export_dtype = "float32";  // "float32" or "float16" (the loaders convert to the parameters' dtype)
  // "" = train the encoder with the decoder. A folder holding ss_encoder.json / ss_encoder.safetensors =
  // load that encoder (its config must equal model.encoder) and keep it frozen: only the decoder trains,
  // on the fixed latent space a Stage 1 was trained on (docs/ss_vae.md, "A decoder for a frozen encoder").
  std::string frozen_encoder;
  static SsVaeModelConfig from(simu::config::Reader& r);
};

// loss: weights of the reconstruction terms on the decoder's occupancy logits, plus the KL weight.
// TRELLIS trains its sparse-structure VAE with one of BCE, L1 (of the sigmoid) or Dice (its released
// config: Dice, lambda_kl 1e-3); here any weighted sum of them. Every term is a mean over samples of
// a per-sample value, so the loss does not depend on how a batch is split over ranks (TRELLIS's Dice
// pools the whole per-GPU batch instead).
struct SsVaeLossConfig {
  double bce = 0.0;         // mean binary cross-entropy with logits over the voxels
  double dice = 1.0;        // 1 - (2 sum(p y) + 1) / (sum p + sum y + 1), p = sigmoid(logits)
  double l1 = 0.0;          // mean |sigmoid(logits) - y|
  double lambda_kl = 1e-3;  // weight of the KL term (mean over latent elements)
  static SsVaeLossConfig from(simu::config::Reader& r);
};

// data: the training shapes (the app draws them from the shape world; data/ss_vae_data.h) and batches.
struct SsVaeDataConfig {
  int64_t resolution = 32;    // occupancy grid R of the decoder's target R^3
  // The encoder's input grid side (0 = resolution). A smaller one (e.g. 16 with resolution 32) trains a
  // decoder with more up-sampling levels than the encoder has down-sampling levels: the latent of the
  // coarse grid decoded to the fine one. resolution = encoder_resolution / down-sampling x up-sampling.
  int64_t encoder_resolution = 0;
  int64_t global_batch = 64;  // shapes per optimizer step over all ranks
  // Training shapes: 0 = a fresh world instance for every sample (an endless stream, nothing repeats);
  // N > 0 = N fixed instances per family, cycled (their grids are cached in memory after first use).
  int64_t train_instances = 0;
  // Families to train on ([] = every family of the world's train split; the held-out one is refused).
  std::vector<std::string> families;
  int64_t workers = 4;   // background threads making shapes and their grids
  int64_t prefetch = 8;  // batches made ahead of the step that trains on them
  uint64_t seed = 0;     // which instances the stream draws (all ranks agree)
  static SsVaeDataConfig from(simu::config::Reader& r);
};

// train: the loop.
struct SsVaeLoopConfig {
  int64_t steps = 20000;
  std::string precision = "bf16";  // "bf16" (CUDA autocast; parameters and optimizer stay fp32) or "fp32"
  uint64_t seed = 0;               // initial weights and the posterior noise
  std::string device = "cuda";     // "cuda" (rank's local GPU) or "cpu"
  double ema_rate = 0.0;           // EMA of the weights (e.g. 0.999; 0 = none): evaluated and exported when on
  // CUDA: cuDNN times its convolution algorithms for the run's fixed shapes and keeps the fastest
  // (the choice may differ between runs; GPU runs are not bit-reproducible anyway: atomics in backward).
  bool cudnn_benchmark = true;
  static SsVaeLoopConfig from(simu::config::Reader& r);
};

// eval: reconstruction IoU of the posterior mean's decode (logits > 0) against the grid.
struct SsVaeEvalConfig {
  int64_t every = 1000;            // steps between validation runs (0 = none); the test split only at the end
  int64_t val_per_family = 16;     // validation instances per training family
  int64_t test_per_family = 64;    // test instances per training family (and of the held-out family)
  int64_t batch = 32;              // shapes per evaluation forward
  static SsVaeEvalConfig from(simu::config::Reader& r);
};

struct SsVaeConfig {
  SsVaeModelConfig model;
  SsVaeLossConfig loss;
  OptimConfig optim;
  SsVaeDataConfig data;
  SsVaeLoopConfig train;
  SsVaeEvalConfig eval;
  RunConfig run;
  DistConfig dist;
  std::string file;     // the config file
  YAML::Node resolved;  // the whole config after --set overrides (saved in checkpoints)
  // Loads a file with "a.b=v" overrides; unknown keys or bad values are errors naming file and key,
  // and so are sections that do not fit together (latent channels, grid sizes).
  static SsVaeConfig load(const std::string& path, const std::vector<std::string>& overrides = {});
  static SsVaeConfig from(simu::config::Reader& r);
  // The encoder's input grid side (data.encoder_resolution, or data.resolution when 0).
  int64_t encoder_resolution() const { return data.encoder_resolution > 0 ? data.encoder_resolution : data.resolution; }
  // The latent grid side: the encoder's input side / its down-sampling factor.
  int64_t latent_resolution() const { return encoder_resolution() / model.encoder.downsample_factor(); }
};

// What a train_ss_vae run writes under run.out_dir (a fresh run refuses them without --overwrite).
const std::vector<std::string>& ss_vae_run_outputs();

}  // namespace simu::training
