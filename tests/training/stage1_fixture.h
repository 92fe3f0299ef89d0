// A tiny Stage-1 setup for the train_stage1 tests: a one-block generator with a 2^3 shape latent, a
// one-block embedder at 28 px / 8 px inputs, 4^3 occupancy, seeded synthetic samples in memory, a
// config (CPU, fp32) and the objective built from them.
#pragma once

#include <torch/torch.h>

#include <filesystem>
#include <fstream>
#include <memory>
#include <string>

#include "data/pair_cache.h"
#include "data/stage1_cache.h"
#include "test_util.h"
#include "training/flow_objective.h"
#include "training/stage1_data.h"
#include "training/trainer.h"

namespace simu::testing {

constexpr int64_t kTinyImage = 28, kTinyPoint = 8, kTinyR = 4;

// The tiny generator (project layout) and embedder (fixture layout) configs in dir.
inline void write_tiny_stage1_models(const std::string& dir) {
  std::filesystem::create_directories(dir);
  std::ofstream(dir + "/generator.yaml") << R"(generator:
  kind: ShortCut
  time_scale: 1000.0
  inference_steps: 4
  rescale_t: 3.0
  no_shortcut: true
  cfg_strength: 7.0
  cfg_interval: [0, 500]
  unconditional_handling: add_flag
flow_model:
  in_channels: 4
  model_channels: 32
  cond_channels: 16
  out_channels: 4
  num_blocks: 1
  num_heads: 2
  mlp_ratio: 2
  qk_rms_norm: true
  share_mod: false
  is_shortcut_model: true
  force_zeros_cond: true
  latents:
    - {name: shape, in_channels: 4, pos_embedder: shape, resolution: 2, patch_size: 1}
    - {name: 6drotation_normalized, in_channels: 6, pos_embedder: learnt, token_len: 1}
    - {name: scale, in_channels: 3, pos_embedder: learnt, token_len: 1}
    - {name: translation, in_channels: 3, pos_embedder: learnt, token_len: 1}
    - {name: translation_scale, in_channels: 1, pos_embedder: learnt, token_len: 1}
  share_groups:
    6drotation_normalized: [6drotation_normalized, scale, translation, translation_scale]
)";
  std::ofstream(dir + "/embedder.json") << R"({
 "vit": {"img_size": 28, "patch_size": 14, "embed_dim": 16, "depth": 1, "num_heads": 2, "mlp_ratio": 2,
         "init_values": 1.0, "ffn_layer": "mlp", "block_chunks": 0, "num_register_tokens": 1},
 "dino_image_input_size": 28,
 "dino_mask_input_size": 28,
 "pointpatch": {"input_size": 8, "patch_size": 4, "embed_dim": 16, "remap_output": "linear",
                "block_heads": 2, "block_mlp_ratio": 2.0},
 "fuser": {"embedder_list": [["dino_image", [["image", "cropped"], ["rgb_image", "full"]]],
                             ["dino_mask", [["mask", "cropped"], ["rgb_image_mask", "full"]]],
                             ["pointpatch", [["pointmap", "cropped"], ["rgb_pointmap", "full"]]]],
           "use_pos_embedding": "learned", "projection_pre_norm": true,
           "projection_net_hidden_dim_multiplier": 1.0}
})";
}

// A training config for the tiny model in out/cfg.yaml (CPU, fp32, seed 7, checkpoints every 2
// steps, random linear targets), with extra YAML appended (e.g. an objective: section).
inline training::Stage1Config tiny_stage1_config(const std::string& out, int64_t steps, int64_t global_batch,
                                                 int64_t micro, const std::string& extra = "") {
  write_tiny_stage1_models(out + "/models");
  const std::string file = out + "/cfg.yaml";
  std::ofstream(file) << "model: {generator: " << out << "/models/generator.yaml, embedder: " << out
                      << "/models/embedder.json}\n"
                         "targets: {kind: random_linear, seed: 3}\n"
                         "optim: {lr: 0.003, warmup_steps: 2, clip_grad_norm: 1.0, weight_decay: 0.01}\n"
                      << "data: {cache: unused.h5, global_batch: " << global_batch << ", micro_batch: " << micro << "}\n"
                      << "train: {steps: " << steps << ", device: cpu, precision: fp32, seed: 7}\n"
                      << "run: {out_dir: " << out << ", checkpoint_every: 2, keep_last: 5, progress: false}\n"
                      << extra;
  return training::Stage1Config::load(file);
}

// n synthetic samples (seeded; training/stage1_data.h) at the tiny sizes; record indices 100 + 3i
// (they need not be contiguous).
inline std::shared_ptr<training::Stage1Samples> tiny_samples(int64_t n, uint64_t seed) {
  auto s = training::synthetic_stage1_samples(n, kTinyImage, kTinyPoint, kTinyR, seed);
  for (int64_t i = 0; i < n; ++i) s->ids[i] = 100 + 3 * i;
  return s;
}

// The objective of a config over samples (a fresh model seeded by model_seed, default cfg.train.seed,
// on device; targets default to the config's).
inline std::unique_ptr<training::FlowObjective> tiny_objective(const training::Stage1Config& cfg,
                                                               std::shared_ptr<const training::Stage1Samples> samples,
                                                               training::ShapeTargetFn targets = nullptr,
                                                               int64_t model_seed = -1,
                                                               torch::Device device = torch::kCPU) {
  auto model = training::make_stage1_model(cfg.model.generator, cfg.model.embedder, "", device,
                                           model_seed < 0 ? cfg.train.seed : static_cast<uint64_t>(model_seed));
  if (!targets)
    targets = training::make_shape_targets(cfg.targets, model->generator->config().backbone.latent("shape"),
                                           samples->occupancy_resolution(), device, cfg.file);
  return std::make_unique<training::FlowObjective>(cfg, model, std::move(samples), std::move(targets), device);
}

}  // namespace simu::testing
