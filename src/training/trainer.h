// FM-DPO training loop: typed config, data sharding contract, gradient accumulation across ranks,
// AdamW + schedule + clipping, bf16 autocast, checkpoints and resume, logs.
#pragma once

#include <torch/torch.h>

#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include <yaml-cpp/yaml.h>

#include "common/config.h"
#include "training/checkpoint.h"
#include "training/distributed.h"
#include "training/fmdpo.h"
#include "training/optim.h"

namespace simu::training {

// model: the base Stage-1 generator.
struct ModelConfig {
  std::string config;   // generator config (official JSON/YAML or project layout)
  std::string weights;  // safetensors with the official names ("" = random init, benchmarks only)
  static ModelConfig from(simu::config::Reader& r);
};

// data: the pair cache and the batch split.
struct DataConfig {
  std::string cache;          // HDF5 pair cache
  int64_t global_batch = 16;  // pairs per optimizer step over all ranks
  int64_t micro_batch = 1;    // pairs per forward/backward; accumulation = global / (micro * world)
  int64_t prefetch = 4;       // batches read ahead by the background thread
  uint64_t seed = 0;          // epoch shuffle seed (all ranks agree)
  static DataConfig from(simu::config::Reader& r);
};

// train: the loop.
struct LoopConfig {
  int64_t steps = 1500;
  std::string precision = "bf16";         // "bf16" (CUDA autocast; adapters stay fp32) or "fp32"
  bool activation_checkpointing = false;  // recompute each transformer block in backward (per-block checkpointing)
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
  static RunConfig from(simu::config::Reader& r);
};

// dist: failure detection.
struct DistConfig {
  double timeout_s = 600;        // every collective and the rendezvous
  double hang_timeout_s = 1800;  // launcher: a rank silent this long is declared hung
  static DistConfig from(simu::config::Reader& r);
};

struct TrainConfig {
  ModelConfig model;
  YAML::Node lora;  // LoRA section, read by the LoRA library (lora::LoraConfig::from, strict)
  ObjectiveConfig objective;
  OptimConfig optim;
  DataConfig data;
  LoopConfig train;
  RunConfig run;
  DistConfig dist;
  std::string file;      // the config file
  YAML::Node resolved;   // the whole config after --set overrides (saved in checkpoints)
  // Loads a file with "a.b=v" overrides; unknown keys or bad values are errors naming file and key.
  static TrainConfig load(const std::string& path, const std::vector<std::string>& overrides = {});
  static TrainConfig from(simu::config::Reader& r);
};

// Outputs of an earlier run in cfg.run.out_dir (checkpoints/, adapter/, metrics.jsonl, tensorboard/):
// a fresh run (not resuming) refuses them unless overwrite (simu::Error naming the config, out_dir
// and what is there); with overwrite the lead process removes them first. Also refuses an empty
// data.cache (naming the config file and key).
void prepare_out_dir(const TrainConfig& cfg, bool resuming, bool overwrite, bool lead);

// One preference pair as the trainer sees it.
struct Pair {
  int64_t id = 0;      // stable record index in the cache (seeds its noise)
  data::PairKind kind = data::PairKind::OcclusionCompletion;
  torch::Tensor x_pos, x_neg;  // [T, C] float32
  torch::Tensor cond;          // [l, Cc] float32 (l may differ between pairs)
};

// Position in the epoch-shuffled stream of global batches.
struct DataPosition {
  int64_t epoch = 0, step = 0;
};

// Source of this rank's share of each global batch (the HDF5 PairStream or an in-memory one).
class PairSource {
 public:
  virtual ~PairSource() = default;
  // This rank's pairs of the next global batch (global_batch / world of them).
  virtual std::vector<Pair> next_batch() = 0;
  // Position of the next batch (what a checkpoint stores).
  virtual DataPosition position() const = 0;
};
// Opens a source for (rank, world, global batch, seed) at a position.
using PairSourceFactory =
    std::function<std::unique_ptr<PairSource>(int rank, int world, int64_t global_batch, uint64_t seed, DataPosition)>;

// In-memory pairs with the stream's contract: each epoch the permutation data::epoch_permutation(n, seed,
// epoch) that the HDF5 PairStream uses too (one order for every source), that
// every rank computes alike; global batch b of the epoch = perm[b*G, (b+1)*G) (the tail that does
// not fill a batch is skipped); rank r takes the contiguous slice [r*G/W, (r+1)*G/W).
class MemoryPairSource : public PairSource {
 public:
  MemoryPairSource(std::shared_ptr<const std::vector<Pair>> pairs, int rank, int world, int64_t global_batch,
                   uint64_t seed, DataPosition start);
  std::vector<Pair> next_batch() override;
  DataPosition position() const override { return pos_; }

 private:
  std::shared_ptr<const std::vector<Pair>> pairs_;
  int rank_, world_;
  int64_t global_;
  uint64_t seed_;
  DataPosition pos_;
  std::vector<int64_t> perm_;
  int64_t perm_epoch_ = -1;
};

// Metrics of one optimizer step, over all ranks.
struct StepMetrics {
  int64_t step = 0;          // optimizer steps done after this one
  double loss = 0;           // FM-DPO loss (mean of w * per_pair)
  double accuracy = 0;       // share of pairs with d_theta < d_ref
  double margin = 0;         // mean of -beta/2 (d_theta - d_ref) (the logit inside the sigmoid)
  double grad_norm = 0;      // global norm before clipping
  double lr = 0;
  double pairs_per_s = 0;
  // Rank 0's wall time of this step and its phases (each phase waits for the device at its end):
  // waiting for the data stream, forwards + backwards of its micro-batches, the gradient all-reduce
  // (including waiting for the slowest rank), clipping + AdamW.
  double seconds_step = 0, seconds_data = 0, seconds_compute = 0, seconds_allreduce = 0, seconds_optimizer = 0;
  // "<kind>/{policy,ref}_{pos,neg}" mean flow-matching losses per kind ("completion", "preservation").
  std::map<std::string, double> per_kind;
  std::map<std::string, double> scalars() const;
};

// Sums over pairs of one step (this rank's, then every rank's through Communicator::all_reduce_sum):
// the typed form of the metrics reduction. Kinds are indexed 0 occlusion completion, 1 clean preservation.
struct StepSums {
  double loss = 0;     // sum of w * per-pair loss
  double correct = 0;  // pairs with d_theta < d_ref
  double margin = 0;   // sum of -beta/2 (d_theta - d_ref)
  struct PerKind {
    double count = 0, policy_pos = 0, policy_neg = 0, ref_pos = 0, ref_neg = 0;
  } kind[2];
  // Flat layout for the all-reduce: loss, correct, margin, then per kind count and the four losses.
  std::vector<double> pack() const;
  static StepSums unpack(const std::vector<double>& v);
};

class Trainer {
 public:
  // model: adapters injected, on `device`; comm: this rank's communicator.
  Trainer(TrainConfig cfg, PolicyModel& model, PairSourceFactory sources, Communicator& comm, torch::Device device);
  // Restores adapters, optimizer, step, data position and RNG states from a checkpoint directory.
  void resume(const std::string& dir);
  // One optimizer step over one global batch.
  StepMetrics step();
  // Trains up to cfg.train.steps: logs (rank 0), checkpoints every K steps and at the end, exports
  // the adapter (PEFT) to <out_dir>/adapter at the end.
  void run();
  int64_t steps_done() const { return step_; }
  // Everything a checkpoint holds for the current state.
  CheckpointData checkpoint_data() const;
  // Writes a checkpoint now (rank 0 only writes; every rank must call). Returns its dir (rank 0).
  std::string save();
  AdamW& optimizer() { return *opt_; }

 private:
  // Forward and backward over this rank's pairs, one group (micro-batch, one condition length) at a
  // time; gradients accumulate on the adapters. Returns this rank's metric sums.
  StepSums forward_backward(const std::vector<Pair>& pairs);

  TrainConfig cfg_;
  PolicyModel& model_;
  PairSourceFactory make_source_;
  Communicator& comm_;
  torch::Device device_;
  std::unique_ptr<PairSource> source_;
  std::unique_ptr<AdamW> opt_;
  int64_t step_ = 0;
};

}  // namespace simu::training
