// The typed config of a training run (configs/*.yaml): one struct per section, strict keys. The
// sections every run shares (optim, data, train, run, dist: TrainerConfig, what Trainer reads) and
// FM-DPO's own (model, lora, objective: TrainConfig). Stage-1 pretraining's: stage1_config.h.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <yaml-cpp/yaml.h>

#include "common/config.h"
#include "training/fmdpo.h"
#include "training/optim.h"

namespace simu::training {

// model: the base Stage-1 generator.
struct ModelConfig {
  std::string config;   // generator config (official JSON/YAML or project layout)
  std::string weights;  // safetensors with the official names ("" = random init, benchmarks only)
  // The frozen condition embedder, needed (only) for an inputs-mode pair cache (cond_mode inputs):
  // its config (official ss_generator.yaml layout or the fixture JSON) and weights ("" = take them
  // from `weights`, which in the released ss_generator.safetensors hold the embedder too; both ""
  // = random init, benchmarks only).
  std::string embedder_config, embedder_weights;
  static ModelConfig from(simu::config::Reader& r);
};

// data: the cache and the batch split.
struct DataConfig {
  std::string cache;          // HDF5 cache (FM-DPO: pair cache; Stage 1: stage-1 sample cache)
  int64_t global_batch = 16;  // samples (pairs) per optimizer step over all ranks
  int64_t micro_batch = 1;    // samples per forward/backward; accumulation = global / (micro * world)
  int64_t prefetch = 4;       // batches read ahead by the background thread
  uint64_t seed = 0;          // epoch shuffle seed (all ranks agree)
  static DataConfig from(simu::config::Reader& r);
};

// train: the loop.
struct LoopConfig {
  int64_t steps = 1500;
  std::string precision = "bf16";         // "bf16" (CUDA autocast; adapters stay fp32) or "fp32"
  bool activation_checkpointing = false;  // recompute each transformer block in backward (per-block checkpointing)
  // Opt-in FP8 frozen base (models/fp8_linear.h): the LoRA-wrapped base projections run as e4m3 GEMMs
  // (weights quantised once after loading, inputs per call; adapters, loss and optimizer unchanged).
  // Faster, costs fidelity (docs/benchmarks.md "FP8 frozen base" has the measured figures). Needs device cuda with
  // compute capability >= 8.9 and precision bf16.
  bool fp8_base = false;
  std::string fp8_base_backward = "fp8";  // the base's input gradients: "fp8" (e4m3) or "bf16"
  // Its layers: "adapted" (the LoRA-wrapped projections) or "all" (also every other frozen Linear
  // with sizes that are multiples of 16: the MLPs, modulation and timestep layers).
  std::string fp8_base_layers = "adapted";
  uint64_t seed = 0;                      // noise and t seed
  std::string device = "cuda";            // "cuda" (rank's local GPU) or "cpu"
  static LoopConfig from(simu::config::Reader& r);
};

// run: outputs.
struct RunConfig {
  std::string out_dir = "runs/fmdpo";  // checkpoints/, metrics.jsonl, tensorboard/, adapter/
  int64_t checkpoint_every = 250;      // steps; 0 = only at the end
  int keep_last = 3;
  int64_t log_every = 10;              // plain progress lines every N steps (non-TTY)
  bool progress = true;
  // End this run early (with a checkpoint, without the export; continue with --resume latest): after
  // the step that reaches stop_at_step (0: none), or after the first step that ends more than
  // stop_after_s seconds into this run's steps (0: none). The learning-rate schedule stays over
  // train.steps, so runs of any length make the same training.
  int64_t stop_at_step = 0;
  double stop_after_s = 0;
  static RunConfig from(simu::config::Reader& r);
};

// dist: failure detection.
struct DistConfig {
  double timeout_s = 600;        // every collective and the rendezvous
  double hang_timeout_s = 1800;  // launcher: a rank silent this long is declared hung
  static DistConfig from(simu::config::Reader& r);
};

// The sections every training run shares, which Trainer reads.
struct TrainerConfig {
  OptimConfig optim;
  DataConfig data;
  LoopConfig train;
  RunConfig run;
  DistConfig dist;
  std::string file;      // the config file
  YAML::Node resolved;   // the whole config after --set overrides (saved in checkpoints)
  // Reads the shared sections of r (the caller reads its own sections and finishes r).
  void read_shared(simu::config::Reader& r);
};

// An FM-DPO run (train_fmdpo): the shared sections plus the generator, its LoRA and the objective.
struct TrainConfig : TrainerConfig {
  ModelConfig model;
  YAML::Node lora;  // LoRA section, read by the LoRA library (lora::LoraConfig::from, strict)
  ObjectiveConfig objective;
  // Loads a file with "a.b=v" overrides; unknown keys or bad values are errors naming file and key.
  static TrainConfig load(const std::string& path, const std::vector<std::string>& overrides = {});
  static TrainConfig from(simu::config::Reader& r);
};

// Outputs of an earlier run in cfg.run.out_dir (checkpoints/, adapter/, model/, metrics.jsonl,
// tensorboard/): a fresh run (not resuming) refuses them unless overwrite (simu::Error naming the
// config, out_dir and what is there); with overwrite the lead process removes them first. Also
// refuses an empty data.cache (naming the config file and key; `build_hint` says how to make one).
void prepare_out_dir(const TrainerConfig& cfg, bool resuming, bool overwrite, bool lead,
                     const std::string& build_hint = "build one with pairs make / build_pairs");
// The same for any training program: `outputs` (names under out_dir) of an earlier run are refused
// unless overwrite (then removed by the lead process); nothing is checked when resuming.
void prepare_run_dir(const std::string& config_file, const std::string& out_dir, const std::vector<std::string>& outputs,
                     bool resuming, bool overwrite, bool lead);

}  // namespace simu::training
