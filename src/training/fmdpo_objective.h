// FM-DPO as the trainer's objective (objective.h): LoRA adapters of a PolicyModel on preference pairs
// (fmdpo.h for the loss, pair_source.h for the pairs, train_config.h for its config).
#pragma once

#include <torch/torch.h>

#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "training/fmdpo.h"
#include "training/objective.h"
#include "training/pair_source.h"
#include "training/train_config.h"

namespace simu::training {

// Sums over pairs of one step (this rank's, then every rank's): the typed form of FM-DPO's metric
// sums. Kinds are indexed 0 occlusion completion, 1 clean preservation.
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
// on the trainer's device) -> condition tokens [B, L, Cc]. Called under no_grad and in the step's
// precision (bf16 autocast on CUDA when train.precision is bf16). training/cond_inputs.h loads one.
using ConditionEmbedFn = std::function<torch::Tensor(const std::map<std::string, torch::Tensor>& inputs)>;

class FmdpoObjective : public Objective {
 public:
  // model: adapters injected, on `device`; sources: the pairs (opened by open_data).
  FmdpoObjective(TrainConfig cfg, PolicyModel& model, PairSourceFactory sources, torch::Device device);
  std::string name() const override { return "FM-DPO"; }
  std::string sample_noun() const override { return "pairs"; }
  std::vector<std::pair<std::string, torch::Tensor>> parameters() override { return model_.adapter_parameters(); }
  std::string params_file() const override { return "adapter.safetensors"; }
  void open_data(int rank, int world, int64_t global_batch, uint64_t seed, DataPosition position) override;
  DataPosition data_position() const override { return source_->position(); }
  std::unique_ptr<StagedBatch> read_batch(int64_t step, const UploadStream& upload) override;
  // Per group (micro-batch, one condition length): the policy and reference losses, backward of the
  // weighted per-pair loss. Terms [7, pairs]: weighted loss, d_theta, d_ref, policy +/-, reference +/-.
  torch::Tensor forward_backward(StagedBatch& batch) override;
  std::vector<double> metric_sums(const torch::Tensor& terms, const StagedBatch& batch) const override;
  void set_metrics(const std::vector<double>& sums, double n, StepMetrics& m) const override;
  std::string export_result(const std::string& out_dir) override;
  // Pairs that carry condition inputs (an inputs-mode cache) are embedded with fn inside the step;
  // without one, such pairs are an error.
  void set_condition_embedder(ConditionEmbedFn fn) { embed_ = std::move(fn); }

 private:
  TrainConfig cfg_;
  PolicyModel& model_;
  PairSourceFactory make_source_;
  torch::Device device_;
  std::unique_ptr<PairSource> source_;
  ConditionEmbedFn embed_;
};

}  // namespace simu::training
