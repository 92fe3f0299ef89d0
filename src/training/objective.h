// The part of a training run that the step loop swaps: what a step's data is, what its forward and
// backward compute, which parameters it trains and what it reports. FM-DPO (fmdpo_objective.h: LoRA
// adapters on preference pairs) and Stage-1 flow matching (flow_objective.h: the whole model from
// scratch) implement it; Trainer (trainer.h) owns everything else: ranks and the batch split,
// AdamW with its schedule and clipping, the read-ahead, checkpoints and resume, logs and progress.
//
// A step, as the trainer drives it:
//   batch = read_batch(step, upload)        this rank's share of the global batch, staged for the device
//   terms = forward_backward(*batch)        gradients accumulate on parameters(); per-sample terms
//   (next batch read ahead, gradients averaged over ranks, clipped, AdamW)
//   sums  = metric_sums(terms on the host)  summed over ranks, then set_metrics(sums, global batch)
//   after_update(step)                      (EMA)
#pragma once

#include <torch/torch.h>

#include <c10/core/Stream.h>

#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

namespace simu::training {

struct StepMetrics;  // trainer.h

// Position in the epoch-shuffled stream of global batches.
struct DataPosition {
  int64_t epoch = 0, step = 0;
};

// A batch as an objective staged it (its own data lives in a derived struct).
struct StagedBatch {
  virtual ~StagedBatch() = default;
  DataPosition position;  // the data position before this batch (what a checkpoint stores)
  int64_t step = 0;       // the step whose noise it holds
  int64_t samples = 0;    // this rank's share of the global batch
};

// Where a staged batch's host-to-device copies go: the trainer's side CUDA stream (read-ahead), or
// none (each tensor copied with a plain .to(device)).
using UploadStream = c10::optional<c10::Stream>;

class Objective {
 public:
  virtual ~Objective() = default;
  // For log lines ("FM-DPO", "Stage-1 flow matching") and the rate's name ("pairs" -> pairs_per_s).
  virtual std::string name() const = 0;
  virtual std::string sample_noun() const { return "samples"; }
  // The trainable parameters under stable names (AdamW's, and the checkpoint's params file).
  virtual std::vector<std::pair<std::string, torch::Tensor>> parameters() = 0;
  // The checkpoint file that holds them ("adapter.safetensors" or "model.safetensors").
  virtual std::string params_file() const = 0;
  // (Re)opens this rank's data at a position: at the start and at a resume.
  virtual void open_data(int rank, int world, int64_t global_batch, uint64_t seed, DataPosition position) = 0;
  // The position of the next batch read_batch would read.
  virtual DataPosition data_position() const = 0;
  // Reads this rank's share of the next global batch and stages it for step `step` (noise drawn for it,
  // tensors on their way to the device through `upload`).
  virtual std::unique_ptr<StagedBatch> read_batch(int64_t step, const UploadStream& upload) = 0;
  // Forward and backward over a staged batch: the gradients of (sum of the samples' loss terms) /
  // batch.samples accumulate on parameters() (the trainer's all-reduce averages the ranks, so the
  // gradient is that of the global batch's mean). Returns the per-sample metric terms, float32 on the
  // device, [K, samples]: row 0 is each sample's loss term (the step's loss is their sum over all
  // ranks / global batch); the other rows are the objective's. Should not wait for the device.
  virtual torch::Tensor forward_backward(StagedBatch& batch) = 0;
  // This rank's metric sums from forward_backward's terms on the host (float64 [K, samples]), in one
  // fixed layout (the trainer sums them over ranks): [0] is the loss terms' sum.
  virtual std::vector<double> metric_sums(const torch::Tensor& terms, const StagedBatch& batch) const = 0;
  // The step's metrics from every rank's sums over the n samples of the global batch: m.loss and the
  // objective's own (accuracy, margin, per_kind).
  virtual void set_metrics(const std::vector<double>& sums, double n, StepMetrics& m) const = 0;
  // Called after every applied optimizer update; `steps_done` counts it.
  virtual void after_update(int64_t steps_done) { (void)steps_done; }
  // The objective's own state a checkpoint keeps besides parameters and optimizer (EMA weights), and
  // its restore (source: the checkpoint directory, for errors).
  virtual std::map<std::string, torch::Tensor> extra_state() const { return {}; }
  virtual void load_extra_state(const std::map<std::string, torch::Tensor>& state, const std::string& source) {
    (void)state;
    (void)source;
  }
  // Writes the trained result under out_dir at the end of a run (rank 0); returns what it wrote, for
  // the log line ("adapter (PEFT) in runs/x/adapter").
  virtual std::string export_result(const std::string& out_dir) = 0;
};

}  // namespace simu::training
