// FM-DPO training loop: gradient accumulation across ranks, AdamW + schedule + clipping, bf16
// autocast, checkpoints and resume, logs. Its config: train_config.h; its data: pair_source.h.
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
#include "training/pair_source.h"
#include "training/train_config.h"

namespace simu::training {
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
  // reading and staging batches (waiting for the data stream, stacking, noise, issuing the copies: this
  // step's batch when it was not read ahead, and the next one when reading ahead), forwards + backwards
  // of its micro-batches, the gradient all-reduce (including waiting for the slowest rank), clipping +
  // AdamW.
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

// The frozen condition embedder of an inputs-mode run: stacked inputs (kwarg -> [B, ch, S, S] float32
// on the trainer's device) -> condition tokens [B, L, Cc]. The trainer calls it under no_grad and in
// the step's precision (bf16 autocast on CUDA when train.precision is bf16). training/cond_inputs.h
// loads one.
using ConditionEmbedFn = std::function<torch::Tensor(const std::map<std::string, torch::Tensor>& inputs)>;

// A batch whose forward groups' inputs are stacked and on their way to the device (trainer.cpp).
struct StagedBatch;
// What a step hands from its forwards and backwards to its update (trainer.cpp).
struct StepTail;

class Trainer {
 public:
  // model: adapters injected, on `device`; comm: this rank's communicator.
  Trainer(TrainConfig cfg, PolicyModel& model, PairSourceFactory sources, Communicator& comm, torch::Device device);
  ~Trainer();
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
  // Pairs that carry condition inputs (an inputs-mode cache) are embedded with fn inside the step;
  // without one, such pairs are an error.
  void set_condition_embedder(ConditionEmbedFn fn) { embed_ = std::move(fn); }
  // Read-ahead (the fast path; on by default on CUDA, off on the CPU): while a step's backward runs on
  // the device, the next step's batch is read, its noise drawn, and its forward groups stacked into
  // pinned host memory and copied to the device asynchronously on a side CUDA stream (every group of a
  // step up front, each with an event its forward waits for); checkpoints store the data position
  // before that batch. Off (the reference path): each step reads its batch at its start and copies each
  // group with a plain stack(...).to(device). Both give the same pairs, noise and arithmetic (tests).
  void set_read_ahead(bool on) { read_ahead_ = on; }
  // Device-side update (the fast path; on by default, used on CUDA): the gradient all-reduce, the
  // norm, clipping and AdamW follow the backward with no host wait, the update is skipped on the
  // device when the global loss or the norm is not finite, and the step waits once, at its end, for
  // its metrics (the phase times in StepMetrics are then CUDA event times). Off (the reference path):
  // the host reads the metrics and the norm before it issues the update, waiting for the device at
  // each phase's end. Both give bit-identical adapters and metrics (tests/training/trainer_gpu.cpp).
  void set_device_update(bool on) { device_update_ = on; }

 private:
  // Reads the next batch of the source and stages it for step `step` (noise drawn for that step).
  std::unique_ptr<StagedBatch> read_batch(int64_t step);
  // Forward and backward over a staged batch, one group (micro-batch, one condition length) at a time;
  // gradients accumulate on the adapters. Returns the per-pair metric terms ([7, pairs] on the device,
  // rows as in metric_sums) without waiting for the device.
  torch::Tensor forward_backward(StagedBatch& batch);
  // This rank's metric sums of forward_backward's terms (one copy to the host).
  StepSums metric_sums(const torch::Tensor& terms, const std::vector<int>& kinds) const;
  // The adapters' gradients (zeros where a parameter got none).
  std::vector<torch::Tensor> adapter_grads();
  // A step's all-reduce, clipping, update and metrics: the reference path and the device-side one.
  StepMetrics finish_on_host(StepTail& tail);
  StepMetrics finish_on_device(StepTail& tail);
  // Throws (naming the step, the values and the out dir) when the global loss or the norm is not finite.
  void stop_if_non_finite(double global_loss, double grad_norm) const;

  TrainConfig cfg_;
  PolicyModel& model_;
  PairSourceFactory make_source_;
  Communicator& comm_;
  torch::Device device_;
  std::unique_ptr<PairSource> source_;
  std::unique_ptr<AdamW> opt_;
  ConditionEmbedFn embed_;
  int64_t step_ = 0;
  bool read_ahead_;
  bool device_update_ = true;
  std::unique_ptr<StagedBatch> ahead_;  // the next step's batch, read ahead (null: none)
  c10::optional<c10::Stream> upload_stream_;  // the side CUDA stream of the read-ahead uploads
};

}  // namespace simu::training
