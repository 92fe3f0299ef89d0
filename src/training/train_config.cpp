#include "training/train_config.h"

#include <filesystem>

#include <fmt/ranges.h>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "lora/lora_config.h"

namespace simu::training {

namespace stdfs = std::filesystem;

ModelConfig ModelConfig::from(simu::config::Reader& r) {
  ModelConfig c;
  c.config = r.require<std::string>("config");
  r.field("weights", c.weights);
  return c;
}

DataConfig DataConfig::from(simu::config::Reader& r) {
  DataConfig c;
  r.field("cache", c.cache);
  r.field("global_batch", c.global_batch);
  r.field("micro_batch", c.micro_batch);
  r.field("prefetch", c.prefetch);
  r.field("seed", c.seed);
  SIMU_CHECK(c.global_batch >= 1, "{}: data.global_batch must be >= 1, got {}", r.file(), c.global_batch);
  SIMU_CHECK(c.micro_batch >= 1, "{}: data.micro_batch must be >= 1, got {}", r.file(), c.micro_batch);
  SIMU_CHECK(c.prefetch >= 0 && c.prefetch <= 1024, "{}: key 'data.prefetch': expected an integer in 0..1024, got {}",
             r.file(), c.prefetch);
  return c;
}

LoopConfig LoopConfig::from(simu::config::Reader& r) {
  LoopConfig c;
  r.field("steps", c.steps);
  r.field("precision", c.precision);
  r.field("activation_checkpointing", c.activation_checkpointing);
  r.field("seed", c.seed);
  r.field("device", c.device);
  SIMU_CHECK(c.steps >= 1, "{}: train.steps must be >= 1, got {}", r.file(), c.steps);
  SIMU_CHECK(c.precision == "bf16" || c.precision == "fp32", "{}: train.precision: expected 'bf16' or 'fp32', got '{}'",
             r.file(), c.precision);
  SIMU_CHECK(c.device == "cuda" || c.device == "cpu", "{}: train.device: expected 'cuda' or 'cpu', got '{}'", r.file(),
             c.device);
  return c;
}

RunConfig RunConfig::from(simu::config::Reader& r) {
  RunConfig c;
  r.field("out_dir", c.out_dir);
  r.field("checkpoint_every", c.checkpoint_every);
  r.field("keep_last", c.keep_last);
  r.field("log_every", c.log_every);
  r.field("progress", c.progress);
  SIMU_CHECK(c.checkpoint_every >= 0, "{}: run.checkpoint_every must be >= 0", r.file());
  SIMU_CHECK(c.keep_last >= 0, "{}: key 'run.keep_last': expected an integer >= 0 (0 keeps all), got {}", r.file(), c.keep_last);
  SIMU_CHECK(c.log_every >= 1, "{}: key 'run.log_every': expected an integer >= 1, got {}", r.file(), c.log_every);
  SIMU_CHECK(!c.out_dir.empty(), "{}: run.out_dir must not be empty", r.file());
  return c;
}

DistConfig DistConfig::from(simu::config::Reader& r) {
  DistConfig c;
  r.field("timeout_s", c.timeout_s);
  r.field("hang_timeout_s", c.hang_timeout_s);
  for (const auto& [key, v] : {std::pair<const char*, double>{"timeout_s", c.timeout_s}, {"hang_timeout_s", c.hang_timeout_s}})
    SIMU_CHECK(std::isfinite(v) && v > 0 && v <= 7 * 24 * 3600.0,
               "{}: key 'dist.{}': expected a number of seconds in (0, 604800], got {}", r.file(), key, v);
  return c;
}

TrainConfig TrainConfig::from(simu::config::Reader& r) {
  TrainConfig c;
  auto m = r.child("model");
  c.model = ModelConfig::from(m);
  // The lora: section is checked here, naming this file (make_generator_policy reads it again).
  // An absent section stays a null node (the defaults); unknown keys under it are errors (finish()).
  if (r.has("lora")) {
    auto l = r.child("lora");
    (void)simu::lora::LoraConfig::from(l);
    c.lora = YAML::Clone(l.node());
  }
  auto o = r.child("objective");
  c.objective = ObjectiveConfig::from(o);
  auto op = r.child("optim");
  c.optim = OptimConfig::from(op);
  auto d = r.child("data");
  c.data = DataConfig::from(d);
  auto t = r.child("train");
  c.train = LoopConfig::from(t);
  auto rr = r.child("run");
  c.run = RunConfig::from(rr);
  auto ds = r.child("dist");
  c.dist = DistConfig::from(ds);
  r.finish();
  c.file = r.file();
  c.resolved = YAML::Clone(r.node());
  return c;
}

TrainConfig TrainConfig::load(const std::string& path, const std::vector<std::string>& overrides) {
  auto node = simu::config::load_file(path, overrides);
  simu::config::Reader r(node, path);
  return from(r);
}

void prepare_out_dir(const TrainConfig& cfg, bool resuming, bool overwrite, bool lead) {
  if (cfg.data.cache.empty())
    fail_hint("set data.cache in the config or pass --set data.cache=PATH (build one with pairs make / build_pairs)",
              "{}: key 'data.cache' is missing: the pair cache (.h5) to train on", cfg.file);
  if (resuming) return;
  namespace stdfs = std::filesystem;
  const std::string out = cfg.run.out_dir;
  std::vector<std::string> found;
  for (const char* name : {"checkpoints", "adapter", "metrics.jsonl", "tensorboard"})
    if (stdfs::exists(stdfs::path(out) / name)) found.push_back(name);
  if (found.empty()) return;
  if (!overwrite)
    fail_hint("pass --resume latest to continue that run, --overwrite to replace it, or --set run.out_dir=NEW",
              "{}: run.out_dir '{}' already holds an earlier run ({})", cfg.file, out, fmt::join(found, ", "));
  if (!lead) return;
  for (const auto& name : found) simu::fs::remove_tree((stdfs::path(out) / name).string());
  simu::log::info("--overwrite: removed the earlier run's {} from {}", fmt::join(found, ", "), out);
}

}  // namespace simu::training
