// The training loop: gradient accumulation across ranks, AdamW + schedule + clipping, bf16 autocast,
// read-ahead, checkpoints and exact resume, logs. What a step computes is its Objective (objective.h):
// FM-DPO (fmdpo_objective.h) or Stage-1 flow matching (flow_objective.h). Its config: train_config.h.
#pragma once

#include <torch/torch.h>

#include <cmath>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "training/checkpoint.h"
#include "training/distributed.h"
#include "training/fmdpo.h"
#include "training/fmdpo_objective.h"
#include "training/objective.h"
#include "training/optim.h"
#include "training/pair_source.h"
#include "training/train_config.h"

namespace simu::training {

// Metrics of one optimizer step, over all ranks.
struct StepMetrics {
  int64_t step = 0;          // optimizer steps done after this one
  double loss = 0;           // the objective's loss (FM-DPO: mean of w * per_pair)
  double accuracy = NAN;     // FM-DPO: share of pairs with d_theta < d_ref (NaN: not the objective's)
  double margin = NAN;       // FM-DPO: mean of -beta/2 (d_theta - d_ref) (the logit inside the sigmoid)
  double grad_norm = 0;      // global norm before clipping
  double lr = 0;
  double pairs_per_s = 0;    // samples (FM-DPO: pairs) per second, logged under rate_name
  std::string rate_name = "pairs_per_s";
  // Rank 0's wall time of this step and its phases (each phase waits for the device at its end):
  // reading and staging batches (waiting for the data stream, stacking, noise, issuing the copies: this
  // step's batch when it was not read ahead, and the next one when reading ahead), forwards + backwards
  // of its micro-batches, the gradient all-reduce (including waiting for the slowest rank), clipping +
  // AdamW.
  double seconds_step = 0, seconds_data = 0, seconds_compute = 0, seconds_allreduce = 0, seconds_optimizer = 0;
  // The objective's own named means: FM-DPO's "<kind>/{policy,ref}_{pos,neg}" flow-matching losses per
  // kind ("completion", "preservation"); Stage-1 flow matching's per-latent losses (flow_objective.h).
  std::map<std::string, double> per_kind;
  // Every value under its logged name (accuracy and margin only when the objective reports them).
  std::map<std::string, double> scalars() const;
};

// What a step hands from its forwards and backwards to its update (trainer.cpp).
struct StepTail;

class Trainer {
 public:
  // Any objective (its parameters on `device`); comm: this rank's communicator.
  Trainer(TrainerConfig cfg, std::unique_ptr<Objective> objective, Communicator& comm, torch::Device device);
  // FM-DPO (FmdpoObjective): model with adapters injected, on `device`; its pairs from `sources`.
  Trainer(TrainConfig cfg, PolicyModel& model, PairSourceFactory sources, Communicator& comm, torch::Device device);
  ~Trainer();
  // Restores parameters, optimizer, the objective's state, step, data position and RNG states from a
  // checkpoint directory.
  void resume(const std::string& dir);
  // One optimizer step over one global batch.
  StepMetrics step();
  // Trains up to cfg.train.steps: logs (rank 0), checkpoints every K steps and at the end, exports
  // the objective's result (FM-DPO: the PEFT adapter in <out_dir>/adapter) at the end.
  void run();
  int64_t steps_done() const { return step_; }
  // Everything a checkpoint holds for the current state.
  CheckpointData checkpoint_data() const;
  // Writes a checkpoint now (rank 0 only writes; every rank must call). Returns its dir (rank 0).
  std::string save();
  AdamW& optimizer() { return *opt_; }
  Objective& objective() { return *objective_; }
  // FM-DPO: pairs that carry condition inputs (an inputs-mode cache) are embedded with fn inside the
  // step (FmdpoObjective::set_condition_embedder). An error for another objective.
  void set_condition_embedder(ConditionEmbedFn fn);
  // Read-ahead (the fast path; on by default on CUDA, off on the CPU): while a step's backward runs on
  // the device, the next step's batch is read, its noise drawn, and its forward groups stacked into
  // pinned host memory and copied to the device asynchronously on a side CUDA stream (every group of a
  // step up front, each with an event its forward waits for); checkpoints store the data position
  // before that batch. Off (the reference path): each step reads its batch at its start and copies each
  // group with a plain stack(...).to(device). Both give the same samples, noise and arithmetic (tests).
  void set_read_ahead(bool on) { read_ahead_ = on; }
  // Device-side update (the fast path; on by default, used on CUDA): the gradient all-reduce, the
  // norm, clipping and AdamW follow the backward with no host wait, the update is skipped on the
  // device when the global loss or the norm is not finite, and the step waits once, at its end, for
  // its metrics (the phase times in StepMetrics are then CUDA event times). Off (the reference path):
  // the host reads the metrics and the norm before it issues the update, waiting for the device at
  // each phase's end. Both give bit-identical parameters and metrics (tests/training/trainer_gpu.cpp).
  void set_device_update(bool on) { device_update_ = on; }

 private:
  // The parameters' gradients (zeros where a parameter got none).
  std::vector<torch::Tensor> param_grads();
  // A step's all-reduce, clipping, update and metrics: the reference path and the device-side one.
  StepMetrics finish_on_host(StepTail& tail);
  StepMetrics finish_on_device(StepTail& tail);
  // Throws (naming the step, the values and the out dir) when the global loss or the norm is not finite.
  void stop_if_non_finite(double global_loss, double grad_norm) const;

  TrainerConfig cfg_;
  std::unique_ptr<Objective> objective_;
  Communicator& comm_;
  torch::Device device_;
  std::unique_ptr<AdamW> opt_;
  int64_t step_ = 0;
  bool read_ahead_;
  bool device_update_ = true;
  std::unique_ptr<StagedBatch> ahead_;  // the next step's batch, read ahead (null: none)
  c10::optional<c10::Stream> upload_stream_;  // the side CUDA stream of the read-ahead uploads
};

}  // namespace simu::training
