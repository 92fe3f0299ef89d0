// Training of the sparse-structure VAE (train_ss_vae): SparseStructureEncoder + SparseStructureDecoder
// from scratch on filled occupancy grids, with the loss of ss_vae_config.h (TRELLIS's recipe: a
// reconstruction term on the decoder's logits of a posterior sample, plus lambda_kl * KL).
//
// Shared with the FM-DPO trainer: the optimizer, schedule and clipping (optim.h), the ranks and their
// gradient all-reduce (distributed.h, launcher.h), atomic checkpoints with exact resume (checkpoint.h),
// TensorBoard, metrics.jsonl and progress (observe.h), the run/dist config sections and out-dir checks
// (train_config.h). Its data: ss_vae_data.h; its metrics and IoU: ss_vae_eval.h.
//
// A step on CUDA never waits for the host: the batch was made ahead on background threads in pinned
// memory and is copied asynchronously; the all-reduce, clipping, AdamW and the EMA follow the backward
// with no host sync, skipping the update on the device when the loss or the gradient norm is not finite
// (optim.h); the host reads a step's metrics after the next step is issued (run()). On the CPU every
// step reads its metrics before its update (and stops on a non-finite one before touching the weights).
//
// Checkpoint layout (checkpoint.h): adapter.safetensors holds the trained weights under
// "encoder.<official name>" / "decoder.<official name>", optimizer.safetensors the AdamW state of
// those names plus the EMA weights "ema.<name>" when train.ema_rate > 0.
//
// With model.frozen_encoder the encoder is loaded from that folder and never changes (no gradient, no
// AdamW state, no EMA, not in checkpoints; the export copies it): only the decoder trains, e.g. a
// decoder with one more up-sampling level that reads a shipped encoder's latent of a coarser grid.
#pragma once

#include <torch/torch.h>

#include <chrono>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "models/ss_decoder.h"
#include "models/ss_encoder.h"
#include "training/checkpoint.h"
#include "training/distributed.h"
#include "training/optim.h"
#include "training/ss_vae_config.h"
#include "training/ss_vae_data.h"
#include "training/ss_vae_eval.h"

namespace simu::training {

// Metrics of one optimizer step, means over the global batch.
struct SsVaeStepMetrics {
  int64_t step = 0;  // optimizer steps done after this one
  double loss = 0, bce = 0, dice = 0, l1 = 0, kl = 0;
  double iou = 0;  // training batch's reconstruction IoU (of the posterior sample's decode)
  double grad_norm = 0, lr = 0;
  double shapes_per_s = 0;
  double seconds_step = 0;  // wall time since the previous step's metrics (steady state: the step's time)
  double seconds_data = 0;  // time this rank waited for its batch
  std::map<std::string, double> scalars() const;
};

// The official initialisation's one departure from PyTorch's defaults, for training from scratch:
// every ResBlock3d's conv2 zeroed (the official zero_module), so each residual block starts as identity.
void zero_residual_convs(torch::nn::Module& module);

class SsVaeTrainer {
 public:
  // Builds both networks under torch::manual_seed(cfg.train.seed) (every rank alike) on `device`.
  SsVaeTrainer(SsVaeConfig cfg, std::shared_ptr<const ShapeSet> shapes, Communicator& comm, torch::Device device);
  ~SsVaeTrainer();
  // Restores weights, EMA, optimizer and step from a checkpoint directory; the data stream restarts at
  // that step (its samples are a function of the step).
  void resume(const std::string& dir);
  // One optimizer step over one global batch, its metrics read.
  SsVaeStepMetrics step();
  // Trains to cfg.train.steps: logs (rank 0), validation IoU every eval.every steps, checkpoints every
  // run.checkpoint_every steps and at the end; then exports the weights and writes the test table.
  void run();
  // Writes a checkpoint now (rank 0 writes; every rank must call). Returns its dir on rank 0.
  std::string save();
  CheckpointData checkpoint_data() const;
  // Reconstruction IoU of shapes by family, with the EMA weights when train.ema_rate > 0.
  IouTable evaluate(const std::vector<ShapeKey>& keys);
  // Writes <dir>/ss_encoder.{json,safetensors} and ss_decoder.{json,safetensors} (the EMA weights when
  // on, in model.export_dtype), readable by load_ss_encoder / load_ss_decoder. Replaces dir atomically.
  void export_weights(const std::string& dir) const;
  int64_t steps_done() const { return step_; }
  models::SparseStructureEncoder& encoder() { return encoder_; }
  models::SparseStructureDecoder& decoder() { return decoder_; }
  const std::vector<std::pair<std::string, torch::Tensor>>& ema() const { return ema_; }
  // The batch loader's options for a stream starting at start_step (pinned batches on CUDA).
  LoaderOptions loader_options(int64_t start_step) const;

 private:
  // A step issued to the device whose metrics are still there.
  struct Pending {
    int64_t step = 0;
    torch::Tensor values;  // [8]: sums over the global batch / G of total, bce, dice, l1, kl, iou; norm; skip
    double lr = 0, seconds_data = 0;
  };
  Pending issue_step();
  SsVaeStepMetrics finish(const Pending& p);
  // The trained weights as named tensors: "encoder.<name>" (unless frozen), "decoder.<name>" (live).
  std::vector<std::pair<std::string, torch::Tensor>> named_weights() const;
  bool frozen_encoder() const { return !cfg_.model.frozen_encoder.empty(); }
  // Replaces encoder_ by model.frozen_encoder's (strict names and shapes), without gradients.
  void load_frozen_encoder();
  void update_ema(const torch::Tensor& skip);
  // Swaps the EMA weights into the networks (and back: call twice) for evaluation and export.
  void swap_ema();
  void log_scalars(int64_t step, const std::map<std::string, double>& scalars);

  SsVaeConfig cfg_;
  std::shared_ptr<const ShapeSet> shapes_;
  Communicator& comm_;
  torch::Device device_;
  models::SparseStructureEncoder encoder_{nullptr};
  models::SparseStructureDecoder decoder_{nullptr};
  std::unique_ptr<AdamW> opt_;
  std::vector<std::pair<std::string, torch::Tensor>> ema_;  // "ema.<name>" -> float32 on device_
  std::unique_ptr<BatchLoader> loader_;
  int64_t step_ = 0;
  std::chrono::steady_clock::time_point last_finish_;
  struct Logs;
  std::unique_ptr<Logs> logs_;  // rank 0's metrics.jsonl, TensorBoard, progress (run() only)
};

}  // namespace simu::training
