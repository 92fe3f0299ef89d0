// Stage-1 flow matching as the trainer's objective (objective.h): the whole Stage-1 model
// (stage1_model.h) trained from scratch on (condition inputs, target latents) samples, with the
// released FlowMatching / ShortCut recipe (sam3d_objects/model/backbone/generator/flow_matching/model.py,
// shortcut/model.py, classifier_free_guidance.py):
//
//   per sample: t = sigmoid(N(t_mean, t_std)), x0 ~ N(0, I) per latent (shape [T, C], each pose latent
//   [1, k]), x1 = the targets (shape: ShapeTargetFn of the occupancy; pose: the cache's latents),
//   x_t = (1 - (1 - sigma_min) t) x0 + t x1, target = x1 - (1 - sigma_min) x0;
//   condition c = embedder(inputs), times 0 when the sample's condition is dropped (p_unconditional;
//   the model's add_flag + force_zeros_cond handling);
//   v = flow_model(x_t, t * time_scale, c, d) with d = 0 (shortcut models) or none (FlowMatching);
//   loss_b = sum over latents of w_latent * mean((v - target)^2), loss = mean_b loss_b.
//   Shortcut targets (shortcut_fraction > 0): a sample drawn as self-consistency gets d in {1/2^i},
//   the model is asked for step 2d and its target is (s_t + s_{t+d}) / 2 of two d-steps of the model
//   itself (no gradient; CFG on the shape latent for a shortcut_cfg_ratio share); the two kinds are
//   weighted 1 / (1 - f) and shortcut_weight / f, the official mean-per-kind in expectation.
// Every draw of a sample (t, noise, dropout, d) comes from a CPU generator seeded by (train.seed,
// step, record index), so it does not depend on ranks, micro-batches, read-ahead or resume.
// EMA of every parameter after each step; the export writes <out_dir>/model/ss_generator.safetensors.
#pragma once

#include <torch/torch.h>

#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "training/objective.h"
#include "training/pair_source.h"
#include "training/stage1_config.h"
#include "training/stage1_data.h"
#include "training/stage1_model.h"
#include "training/stage1_targets.h"

namespace simu::training {

// One sample's draws at one step.
struct SampleDraws {
  torch::Tensor t;                  // [] float32 in (0, 1)
  std::vector<torch::Tensor> eps;   // per latent (flow model order) [T_l, C_l] N(0, 1)
  bool drop_condition = false;      // condition dropped (CFG training)
  float d = 0;                      // shortcut step: 0 (flow matching) or 1/2^i, i < 8
  bool cfg_target = false;          // a shortcut target made with CFG
};
// Draws, in this order from sample_generator(seed, step, sample_id): t, each latent's noise, then four
// uniforms (dropout, shortcut, its step index, CFG target), always all four.
SampleDraws draw_sample(uint64_t seed, int64_t step, int64_t sample_id,
                        const std::vector<std::vector<int64_t>>& latent_shapes, const FlowObjectiveConfig& config);

class FlowObjective : public Objective {
 public:
  // model: on `device` (make_stage1_model); samples: the training split in memory; targets: the shape
  // latent maker. Checks the config against the model (latent weights name its latents, shortcut
  // targets need a shortcut model) and the samples (occupancy side, pose latents).
  FlowObjective(Stage1Config cfg, Stage1Model model, std::shared_ptr<const Stage1Samples> samples,
                ShapeTargetFn targets, torch::Device device);
  std::string name() const override { return "Stage-1 flow matching"; }
  std::string sample_noun() const override { return "samples"; }
  std::vector<std::pair<std::string, torch::Tensor>> parameters() override { return model_->named_weights(); }
  std::string params_file() const override { return "model.safetensors"; }
  void open_data(int rank, int world, int64_t global_batch, uint64_t seed, DataPosition position) override;
  DataPosition data_position() const override { return order_->position(); }
  std::unique_ptr<StagedBatch> read_batch(int64_t step, const UploadStream& upload) override;
  // Terms [4 + latents, samples]: weighted loss, each latent's mean squared error, condition dropped,
  // shortcut sample, the shape target's mean square.
  torch::Tensor forward_backward(StagedBatch& batch) override;
  std::vector<double> metric_sums(const torch::Tensor& terms, const StagedBatch& batch) const override;
  // loss; per_kind: "loss/<latent>" (mean squared error, all samples), "condition_dropped" and
  // "shortcut_share" (shares of the batch), "target/shape_rms" (root mean square of the shape targets).
  void set_metrics(const std::vector<double>& sums, double n, StepMetrics& m) const override;
  void after_update(int64_t steps_done) override;
  std::map<std::string, torch::Tensor> extra_state() const override;
  void load_extra_state(const std::map<std::string, torch::Tensor>& state, const std::string& source) override;
  // <out_dir>/model/ss_generator.safetensors (export.weights: EMA or raw, export.dtype; buffers too)
  // and the two config files beside it.
  std::string export_result(const std::string& out_dir) override;
  Stage1Model& model() { return model_; }
  // The EMA weights by released name (on the device).
  const std::vector<std::pair<std::string, torch::Tensor>>& ema() const { return ema_; }

 private:
  // The shortcut self-consistency targets of s rows (no gradient): per latent [s, T, C]; x_t, t, d
  // (step in [0, 1] units), cond of those rows; cfg_idx: the rows (of the s) whose shape target is
  // guided (int64, may be empty).
  std::vector<torch::Tensor> shortcut_targets(const std::vector<torch::Tensor>& x_t, const torch::Tensor& t,
                                              const torch::Tensor& d, const torch::Tensor& cond,
                                              const torch::Tensor& cfg_idx);
  // Velocities of every latent (flow model order), float32; t in [0, 1], d the shortcut step in [0, 1]
  // units (shortcut models; ignored otherwise); both scaled by time_scale here.
  std::vector<torch::Tensor> velocity(const std::vector<torch::Tensor>& x, const torch::Tensor& t,
                                      const torch::Tensor& cond, const torch::Tensor& d);

  Stage1Config cfg_;
  Stage1Model model_;
  std::shared_ptr<const Stage1Samples> samples_;
  ShapeTargetFn targets_;
  torch::Device device_;
  std::vector<std::string> latents_;             // flow model order
  std::vector<std::vector<int64_t>> shapes_;     // [T_l, C_l] per latent
  std::unique_ptr<EpochOrder> order_;
  std::vector<std::pair<std::string, torch::Tensor>> ema_;
  bool shortcut_model_ = false;
};

}  // namespace simu::training
