#include "training/train_config.h"

#include <cmath>
#include <filesystem>
#include <initializer_list>
#include <limits>

#include <fmt/ranges.h>

#include "common/config_check.h"
#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "lora/lora_config.h"

namespace simu::training {

namespace stdfs = std::filesystem;

namespace {

using simu::config::choice_field;
using simu::config::int_field;

// Reads a number of seconds (when present) in (0, one week].
void seconds_field(simu::config::Reader& r, const char* key, double& value) {
  r.field(key, value);
  SIMU_CHECK(std::isfinite(value) && value > 0 && value <= 7 * 24 * 3600.0,
             "{}: key '{}': expected a number of seconds in (0, 604800], got {}", r.file(), r.full(key), value);
}

// The section `name` of r, read with T::from.
template <class T>
T section(simu::config::Reader& r, const char* name) {
  auto s = r.child(name);
  return T::from(s);
}

}  // namespace

ModelConfig ModelConfig::from(simu::config::Reader& r) {
  ModelConfig c;
  c.config = r.require<std::string>("config");
  r.field("weights", c.weights);
  r.field("embedder_config", c.embedder_config);
  r.field("embedder_weights", c.embedder_weights);
  return c;
}

DataConfig DataConfig::from(simu::config::Reader& r) {
  DataConfig c;
  r.field("cache", c.cache);
  int_field(r, "global_batch", c.global_batch, 1);
  int_field(r, "micro_batch", c.micro_batch, 1);
  int_field(r, "prefetch", c.prefetch, 0, 1024);
  r.field("seed", c.seed);
  return c;
}

LoopConfig LoopConfig::from(simu::config::Reader& r) {
  LoopConfig c;
  int_field(r, "steps", c.steps, 1);
  choice_field(r, "precision", c.precision, {"bf16", "fp32"});
  r.field("activation_checkpointing", c.activation_checkpointing);
  r.field("fp8_base", c.fp8_base);
  choice_field(r, "fp8_base_backward", c.fp8_base_backward, {"fp8", "bf16"});
  choice_field(r, "fp8_base_layers", c.fp8_base_layers, {"adapted", "all"});
  r.field("seed", c.seed);
  choice_field(r, "device", c.device, {"cuda", "cpu"});
  // The FP8 base runs on FP8 tensor cores inside bf16 autocast (the GPU's capability is checked when
  // the model is made: make_generator_policy).
  if (c.fp8_base)
    SIMU_CHECK(c.device == "cuda" && c.precision == "bf16",
               "{}: key '{}': the FP8 frozen base needs train.device cuda and train.precision bf16 (got {} and {}); "
               "set it to false for this run",
               r.file(), r.full("fp8_base"), c.device, c.precision);
  return c;
}

RunConfig RunConfig::from(simu::config::Reader& r) {
  RunConfig c;
  r.field("out_dir", c.out_dir);
  int_field(r, "checkpoint_every", c.checkpoint_every, 0);
  int_field(r, "keep_last", c.keep_last, 0);  // 0 keeps all
  int_field(r, "log_every", c.log_every, 1);
  r.field("progress", c.progress);
  int_field(r, "stop_at_step", c.stop_at_step, 0);
  r.field("stop_after_s", c.stop_after_s);
  SIMU_CHECK(std::isfinite(c.stop_after_s) && c.stop_after_s >= 0, "{}: key '{}': expected a number of seconds >= 0, got {}",
             r.file(), r.full("stop_after_s"), c.stop_after_s);
  SIMU_CHECK(!c.out_dir.empty(), "{}: key '{}' must not be empty", r.file(), r.full("out_dir"));
  return c;
}

DistConfig DistConfig::from(simu::config::Reader& r) {
  DistConfig c;
  seconds_field(r, "timeout_s", c.timeout_s);
  seconds_field(r, "hang_timeout_s", c.hang_timeout_s);
  return c;
}

TrainConfig TrainConfig::from(simu::config::Reader& r) {
  TrainConfig c;
  c.model = section<ModelConfig>(r, "model");
  // The lora: section is checked here, naming this file (make_generator_policy reads it again).
  // An absent section stays a null node (the defaults); unknown keys under it are errors (finish()).
  if (r.has("lora")) {
    auto l = r.child("lora");
    (void)simu::lora::LoraConfig::from(l);
    c.lora = YAML::Clone(l.node());
  }
  c.objective = section<ObjectiveConfig>(r, "objective");
  c.read_shared(r);
  r.finish();
  return c;
}

void TrainerConfig::read_shared(simu::config::Reader& r) {
  optim = section<OptimConfig>(r, "optim");
  data = section<DataConfig>(r, "data");
  train = section<LoopConfig>(r, "train");
  run = section<RunConfig>(r, "run");
  dist = section<DistConfig>(r, "dist");
  file = r.file();
  resolved = YAML::Clone(r.node());
}

TrainConfig TrainConfig::load(const std::string& path, const std::vector<std::string>& overrides) {
  auto node = simu::config::load_file(path, overrides);
  simu::config::Reader r(node, path);
  return from(r);
}

void prepare_out_dir(const TrainerConfig& cfg, bool resuming, bool overwrite, bool lead, const std::string& build_hint) {
  if (cfg.data.cache.empty())
    fail_hint(fmt::format("set data.cache in the config or pass --set data.cache=PATH ({})", build_hint),
              "{}: key 'data.cache' is missing: the cache (.h5) to train on", cfg.file);
  prepare_run_dir(cfg.file, cfg.run.out_dir, {"checkpoints", "adapter", "model", "metrics.jsonl", "tensorboard"},
                  resuming, overwrite, lead);
}

void prepare_run_dir(const std::string& config_file, const std::string& out, const std::vector<std::string>& outputs,
                     bool resuming, bool overwrite, bool lead) {
  if (resuming) return;
  std::vector<std::string> found;
  for (const auto& name : outputs)
    if (stdfs::exists(stdfs::path(out) / name)) found.push_back(name);
  if (found.empty()) return;
  if (!overwrite)
    fail_hint("pass --resume latest to continue that run, --overwrite to replace it, or --set run.out_dir=NEW",
              "{}: run.out_dir '{}' already holds an earlier run ({})", config_file, out, fmt::join(found, ", "));
  if (!lead) return;
  for (const auto& name : found) simu::fs::remove_tree((stdfs::path(out) / name).string());
  simu::log::info("--overwrite: removed the earlier run's {} from {}", fmt::join(found, ", "), out);
}

}  // namespace simu::training
