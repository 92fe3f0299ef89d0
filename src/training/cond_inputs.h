// Training on an inputs-mode pair cache (docs/pair_cache.md, cond_mode "inputs"): the cache stores
// the condition embedder's inputs, and the frozen condition embedder (models/cond_embedder.h) makes
// the condition tokens inside each step (no gradient, the step's precision; Trainer::group_condition).
//
//   auto cfg = TrainConfig::load("configs/lora64.yaml");     // model.embedder_config: ...
//   Trainer trainer(cfg, *model, pair_cache_source(cfg.data.cache, cfg.data.prefetch), *comm, device);
//   attach_condition_embedder(trainer, cfg, device);          // no-op for a tokens-mode cache
#pragma once

#include <torch/torch.h>

#include "data/pair_cache.h"
#include "models/cond_embedder.h"
#include "training/train_config.h"
#include "training/trainer.h"

namespace simu::training {

// The embedder as the trainer calls it: inputs (kwarg -> [B, ch, S, S]) -> tokens [B, L, Cc].
ConditionEmbedFn condition_embed_fn(models::CondEmbedder embedder);

// Loads the frozen embedder of cfg.model (embedder_config; embedder_weights, else weights, else a
// random init when both are "") on device and checks that it makes the cache's tokens
// (cache.cond_shape = [L, Cc]). Throws simu::Error naming the config file and key when
// embedder_config is missing, or the cache and embedder disagree.
models::CondEmbedder load_condition_embedder(const TrainConfig& cfg, const data::CacheInfo& cache, torch::Device device);

// For the programs: reads cfg.data.cache's info; an inputs-mode cache gets its embedder attached to
// the trainer; a tokens-mode cache with model.embedder_config set logs that the embedder is unused.
void attach_condition_embedder(Trainer& trainer, const TrainConfig& cfg, torch::Device device);

}  // namespace simu::training
