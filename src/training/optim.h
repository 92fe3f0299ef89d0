// Optimisation pieces of FM-DPO training: learning-rate schedule, global-norm clipping, AdamW over
// named adapter parameters with its state saved to and restored from named tensors.
#pragma once

#include <torch/torch.h>

#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "common/config.h"

namespace simu::training {

// optim: section of the training config.
struct OptimConfig {
  double lr = 1e-5;
  std::vector<double> betas = {0.9, 0.999};
  double eps = 1e-8;
  double weight_decay = 0.01;
  int64_t warmup_steps = 300;
  std::string schedule = "constant";  // "constant" or "cosine" after the warm-up
  double min_lr_ratio = 0.0;          // cosine floor as a fraction of lr
  double clip_grad_norm = 1.0;        // <= 0: no clipping (the norm is still reported)
  static OptimConfig from(simu::config::Reader& r);
};

// Learning rate for optimizer step `step` (0-based) of `total_steps`: linear warm-up from lr/warmup
// to lr over warmup_steps steps (step s uses lr*(s+1)/warmup), then constant or cosine down to
// lr*min_lr_ratio at the last step.
double learning_rate(const OptimConfig& cfg, int64_t step, int64_t total_steps);

// Global L2 norm over all defined gradients, like torch's clip_grad_norm_: per-tensor norms in float64
// on the CPU; on CUDA per-tensor float32 norms in one multi-tensor launch, summed in float64 on the
// device, one host sync.
double global_grad_norm(const std::vector<torch::Tensor>& params);
// Scales gradients by min(1, max_norm / (norm + 1e-6)) when max_norm > 0 (PyTorch's rule).
// Returns the norm before clipping.
double clip_grad_norm(const std::vector<torch::Tensor>& params, double max_norm);
// The same on CUDA without a host sync (the trainer's device-side update): returns the norm before
// clipping as a 0-dim float64 tensor on the gradients' device, and (max_norm > 0) multiplies every
// gradient by min(1, max_norm / (norm + 1e-6)), computed in float64 on the device and applied in the
// gradients' dtype: the same arithmetic as clip_grad_norm, whose host branch skips the multiply by 1.
// A non-finite norm makes the coefficient NaN (the update is then skipped: AdamW::step's skip).
// Needs CUDA gradients of one dtype (error otherwise).
torch::Tensor clip_grad_norm_on_device(const std::vector<torch::Tensor>& params, double max_norm);

// AdamW on named parameters (decoupled weight decay, PyTorch's torch.optim.AdamW update).
// CPU parameters: torch::optim::AdamW (the fixture-checked reference). CUDA parameters (float32): the
// fused multi-tensor kernel of torch.optim.AdamW(fused=True) (at::_fused_adamw_), a handful of launches
// per step instead of ~10 per tensor; the same update up to float rounding (test_training_gpu checks
// it against the reference). The path follows the first parameter's device; all must share it.
// Both keep the same state_dict layout, so a checkpoint resumes on either.
class AdamW {
 public:
  AdamW(std::vector<std::pair<std::string, torch::Tensor>> params, const OptimConfig& cfg);
  // One update with learning rate lr.
  void step(double lr);
  // CUDA only: the update skipped on the device where skip (0-dim float32 on the parameters' device)
  // is nonzero: parameters, moments and step counts then stay as they were, with no host sync
  // (at::_fused_adamw_'s found_inf; the step counts advance by 1 - skip).
  void step(double lr, const torch::Tensor& skip);
  void zero_grad();
  const std::vector<std::pair<std::string, torch::Tensor>>& params() const { return params_; }
  std::vector<torch::Tensor> tensors() const;
  // State as named CPU tensors: `<name>.exp_avg`, `<name>.exp_avg_sq`, `<name>.step` (int64 scalar).
  std::map<std::string, torch::Tensor> state_dict() const;
  // Restores state_dict(); every parameter's three entries must be there with the right shape.
  void load_state_dict(const std::map<std::string, torch::Tensor>& state, const std::string& source);

 private:
  void fused_step(double lr, const c10::optional<torch::Tensor>& skip);

  std::vector<std::pair<std::string, torch::Tensor>> params_;
  std::unique_ptr<torch::optim::AdamW> opt_;  // CPU path only
  // CUDA path: moments and step count (a float32 device scalar, as the fused kernel takes it) per
  // parameter index, made at the parameter's first step.
  struct FusedState {
    torch::Tensor exp_avg, exp_avg_sq, step;
  };
  std::map<size_t, FusedState> fused_state_;
  OptimConfig cfg_;
  bool fused_ = false;
};

}  // namespace simu::training
