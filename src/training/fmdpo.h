// The FM-DPO objective (SimuScene Sec. 3.4 + supplementary "SAM3D Fine-tuning Details").
//
// For each preference pair (x+, x-) with condition c and weight w:
//   t ~ logit-normal(0, 1) (one per pair), eps+, eps- ~ N(0, I) (separate),
//   x_t = (1 - t) eps + t x,  target = x - eps,
//   L(x) = mean over tokens and channels of (v(x_t, 1000 t, c, d = 0)_shape - target)^2,
//   d_theta = L_policy(x+) - L_policy(x-)   (adapters on),
//   d_ref   = L_ref(x+) - L_ref(x-)         (adapters off, no graph, same t and noise),
//   per_pair = -log sigmoid(-beta/2 (d_theta - d_ref)),  loss = mean_b(w_b per_pair_b).
// Only the shape latent is scored; pose latents are fed by the model binding but never scored.
#pragma once

#include <torch/torch.h>

#include <functional>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "common/config.h"
#include "data/pair_cache.h"

namespace simu::training {

// The network side of FM-DPO training. The binding to the Stage-1 generator with LoRA lives in
// training/generator_policy.h; tests use small stand-ins.
class PolicyModel {
 public:
  virtual ~PolicyModel() = default;
  // Velocity prediction for the shape latent. x_shape: [B, T, C] noised shape latent; t_scaled: [B]
  // (t * 1000); cond: [B, L, Cc] condition tokens; d: [B] (0 = no shortcut). -> [B, T, C].
  virtual torch::Tensor predict_shape(const torch::Tensor& x_shape, const torch::Tensor& t_scaled,
                                      const torch::Tensor& cond, const torch::Tensor& d) = 0;
  // True when predict_shape accepts cond with fewer rows than x_shape: cond [B, L, Cc] for x_shape
  // [B*G, T, C], row b*G + g conditioned on cond[b] (fmdpo_terms stacks the members pair-major: row 2b
  // is pair b's x+, row 2b + 1 its x-). fmdpo_terms then passes each pair's condition once for both
  // members (its projections run once, not twice); false (default): cond repeated per row
  // (rows 2b and 2b + 1 get cond[b]).
  virtual bool shares_condition() const { return false; }
  // Adapters on (policy) or off (reference).
  virtual void set_adapters_enabled(bool enabled) = 0;
  // Trainable adapter parameters under their PEFT names (base_model.model.<path>.lora_A.weight).
  virtual std::vector<std::pair<std::string, torch::Tensor>> adapter_parameters() = 0;
  // Writes the adapter in PEFT format (adapter_config.json + adapter_model.safetensors) into dir.
  virtual void export_peft(const std::string& dir) = 0;
  // Per-block activation checkpointing of later predict_shape calls (each transformer block keeps
  // only its inputs and recomputes in backward). Returns false when the model has no blocks to
  // checkpoint (fmdpo_terms then checkpoints the whole forward as one segment).
  virtual bool set_block_checkpointing(bool enabled) {
    (void)enabled;
    return false;
  }
};

// objective: section of the training config.
struct ObjectiveConfig {
  double beta = 500.0;
  double weight_completion = 1.0;    // data::PairKind::OcclusionCompletion
  double weight_preservation = 0.1;  // data::PairKind::CleanPreservation
  double t_mean = 0.0, t_std = 1.0;  // logit-normal training-time sampler
  static ObjectiveConfig from(simu::config::Reader& r);
  double weight_of(data::PairKind kind) const;
};

// Inputs of one FM-DPO evaluation (all on the model's device).
struct FmdpoInputs {
  torch::Tensor x_pos, x_neg;      // [B, T, C] preferred / rejected shape latents
  torch::Tensor cond;              // [B, L, Cc]
  torch::Tensor w;                 // [B] pair weights
  torch::Tensor t;                 // [B] in (0, 1)
  torch::Tensor eps_pos, eps_neg;  // [B, T, C]
};

// Per-pair terms ([B] each, float32) and the batch loss.
struct FmdpoTerms {
  torch::Tensor loss_pos_policy, loss_neg_policy;  // with graph
  torch::Tensor loss_pos_ref, loss_neg_ref;        // no graph
  torch::Tensor d_theta, d_ref, per_pair;
  torch::Tensor loss;  // scalar mean(w * per_pair)
};

// Evaluates the objective. The policy runs on both members in one batch of 2B rows, pair-major (x+_0,
// x-_0, x+_1, x-_1, ...; each row's arithmetic is the same as alone); the reference too
// (adapters switched off inside, restored on exit, even on error). checkpoint: activation
// checkpointing of the policy forward, per transformer block when the model supports it
// (PolicyModel::set_block_checkpointing), else of the whole forward (see checkpointed()).
FmdpoTerms fmdpo_terms(PolicyModel& model, const FmdpoInputs& in, double beta, bool checkpoint = false);

// Flow-matching MSE per sample: mean over all but dim 0 of (pred - target)^2, in float32. -> [B]
torch::Tensor flow_mse(const torch::Tensor& pred, const torch::Tensor& target);

// A segment of a forward: fn(inputs) -> outputs.
using SegmentFn = std::function<std::vector<torch::Tensor>(const std::vector<torch::Tensor>&)>;
// Activation checkpointing as a custom autograd function: runs fn(inputs) under no-grad (keeping only
// inputs and params) and recomputes it in backward with grad on, the same autocast state and the same
// CPU/CUDA RNG states (dropout draws the same masks; the generators are restored afterwards), then
// returns the gradients for inputs and params (tensors fn reads that require grad, e.g. adapter
// weights; autograd accumulates them into .grad). Under no-grad mode it just runs fn.
std::vector<torch::Tensor> checkpointed_segment(const SegmentFn& fn, const std::vector<torch::Tensor>& inputs,
                                                const std::vector<torch::Tensor>& params);
// Same for a single-output segment.
torch::Tensor checkpointed(const std::function<torch::Tensor(const std::vector<torch::Tensor>&)>& fn,
                           const std::vector<torch::Tensor>& inputs, const std::vector<torch::Tensor>& params);

// Per-pair noise, independent of rank, micro-batch and resume: a CPU generator seeded from
// (seed, step, pair id) draws t (logit-normal) then eps+ then eps-, each [T, C] float32.
struct PairNoise {
  torch::Tensor t;                 // [] float32
  torch::Tensor eps_pos, eps_neg;  // [T, C]
};
PairNoise draw_pair_noise(uint64_t seed, int64_t step, int64_t pair_id, at::IntArrayRef latent_shape,
                          double t_mean, double t_std);

}  // namespace simu::training
