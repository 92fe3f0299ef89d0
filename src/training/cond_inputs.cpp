// Inputs-mode training: the frozen condition embedder inside the step (cond_inputs.h).
#include "training/cond_inputs.h"

#include <fmt/ranges.h>

#include <algorithm>

#include "common/error.h"
#include "common/log.h"

namespace simu::training {

ConditionEmbedFn condition_embed_fn(models::CondEmbedder embedder) {
  return [embedder](const std::map<std::string, torch::Tensor>& inputs) mutable { return embedder->forward(inputs); };
}

models::CondEmbedder load_condition_embedder(const TrainConfig& cfg, const data::CacheInfo& cache, torch::Device device) {
  const auto& m = cfg.model;
  if (m.embedder_config.empty())
    fail_hint("set model.embedder_config to the condition embedder's config (e.g. configs/cond_embedder_sam3d_stage1.yaml) "
              "and model.embedder_weights (default: model.weights)",
              "{}: key 'model.embedder_config' is missing, and the pair cache '{}' stores condition inputs (cond_mode "
              "inputs), which the frozen condition embedder turns into tokens at training time",
              cfg.file, cache.path);
  // The tokens it makes, from its config, before any weights are read.
  const auto config = models::CondEmbedderConfig::load(m.embedder_config);
  const std::vector<int64_t> made{config.num_tokens(), config.embed_dims()};
  if (made != cache.cond_shape)
    fail_hint("train with the embedder the cache was built for (build_pairs --embedder-config)",
              "{}: the condition embedder {} makes [{}, {}] tokens, the pair cache '{}' was built for [{}, {}]", cfg.file,
              m.embedder_config, made[0], made[1], cache.path, cache.cond_shape.at(0), cache.cond_shape.at(1));
  const std::string& weights = m.embedder_weights.empty() ? m.weights : m.embedder_weights;
  models::CondEmbedder embedder{nullptr};
  try {
    embedder = models::load_cond_embedder(m.embedder_config, weights, "auto", device);
  } catch (const Error& e) {
    if (!m.embedder_weights.empty() || weights.empty()) throw;
    throw Error(fmt::format("{}: model.embedder_weights is not set, so the condition embedder's weights were read from "
                            "model.weights '{}': {}", cfg.file, weights, e.what()),
                "set model.embedder_weights to the embedder's safetensors (the released ss_generator.safetensors holds "
                "both, under _base_models.condition_embedder.)");
  }
  const auto names = embedder->input_names();
  for (const auto& name : names) {
    const auto& stored = data::condition_input_names();
    SIMU_CHECK(std::find(stored.begin(), stored.end(), name) != stored.end(),
               "{}: the condition embedder {} reads '{}', which an inputs-mode pair cache does not store", cfg.file,
               m.embedder_config, name);
  }
  log::info("condition embedder {} ({}) runs in the step: {} tokens x {} channels from {}", m.embedder_config,
            weights.empty() ? "random weights" : weights, made[0], made[1], fmt::join(names, ", "));
  return embedder;
}

void attach_condition_embedder(Trainer& trainer, const TrainConfig& cfg, torch::Device device) {
  const auto info = data::PairCacheReader::open(cfg.data.cache).info();
  if (!info.inputs_mode()) {
    if (!cfg.model.embedder_config.empty())
      log::warn("{}: model.embedder_config is set but the pair cache '{}' stores condition tokens: the embedder is not used",
                cfg.file, cfg.data.cache);
    return;
  }
  trainer.set_condition_embedder(condition_embed_fn(load_condition_embedder(cfg, info, device)));
}

}  // namespace simu::training
